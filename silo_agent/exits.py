"""Exit statuses of the `silo-agent` commands (sysexits.h where one fits), in a module with
no imports so that any command can name them without loading pydantic or numpy."""

EX_FAILED = 1  # an operation failed (no camera, a write, a processing error)
EX_USAGE = 2  # bad command line (argparse's own status)
EX_DATAERR = 65  # bad input data: a scan directory that does not follow silo-scan/1
EX_CONFIG = 78  # bad configuration: a config file, settings or a detection model
