"""Pure evaluation above the algorithms: a scan's analysis (reconstruction + detection), the
alarms evaluated on its result and calibration drift. No I/O, no clocks."""
