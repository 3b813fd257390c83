"""Run logs (`felis.logs`): MCAP files written and read back, and what is made from them.

    runlog.py      JsonMcapWriter (the one MCAP writer), RunLog, read_log, log_info: a control run's log
    monitorlog.py  MonitorExport: the servo monitor's CSV and MCAP export (``felis monitor``)
    plot.py        plot_log: a one-page PNG overview of a run log
"""
