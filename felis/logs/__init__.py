"""Run logs (`felis.logs`): MCAP files written and read back, and what is made from them.

    mcap.py        McapLog: the one MCAP writer (Foxglove SDK; chunked, indexed, live view)
    background.py  Background: the writer thread that encodes and writes a log while the loop is in C code
    runlog.py      RunLog: a control run's log (its channels, what a log holds, the crash bound)
    reader.py      read_log → LogData, channel_messages, log_info: a log read back
    schemas.py     JSON schemas by Foxglove's rules for felis's JSON channels
    messages.py    felis's Protobuf messages (/imu, /contacts, /base, /timing)
    wire.py        the per-tick Protobuf messages (joint states, transforms) filled into templates
    skills.py      the skills' channels: /balance (the XCoM monitor) and /phase (the gait phase)
    live.py        LiveView: the same channels over the Foxglove WebSocket protocol (``--live``)
    monitorlog.py  MonitorExport: the servo monitor's CSV and MCAP export (``felis monitor``)
    export.py      a run log as CSV files (``felis log export``)
    plot.py        plot_log: a one-page PNG overview of a run log
    compare.py     two runs compared joint by joint (``felis replay``)
"""
