"""Run logs (`felis.logs`): MCAP files written and read back, and what is made from them.

    runlog.py      McapLog (the one MCAP writer, Foxglove SDK), RunLog, read_log, log_info: a control run's log
    wire.py        the per-tick Protobuf messages (joint states, transforms) filled into templates
    skills.py      the skills' channels: /balance (the XCoM monitor) and /phase (the gait phase)
    live.py        LiveView: the same channels over the Foxglove WebSocket protocol (``--live``)
    monitorlog.py  MonitorExport: the servo monitor's CSV and MCAP export (``felis monitor``)
    export.py      a run log as CSV files (``felis log export``)
    plot.py        plot_log: a one-page PNG overview of a run log
"""
