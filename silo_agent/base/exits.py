"""Exit statuses of every `silo-agent` command, in one place (sysexits.h where one fits); no
imports, so any command can name them without loading pydantic or numpy.

systemd's `RestartPreventExitStatus=` lists DATA_ERROR and CONFIG_ERROR: restarting cannot fix
a bad file, so the unit stays failed until someone edits it.
"""

OK = 0
FAILURE = 1  # an operation that failed on good input (no camera, a write that failed, ...)
USAGE = 2  # argparse's own status for bad command-line arguments
DATA_ERROR = 65  # EX_DATAERR: a scan directory, cloud or manifest that cannot be used
CONFIG_ERROR = 78  # EX_CONFIG: a configuration file that cannot be used
INTERRUPTED = 130  # Ctrl-C
OUTPUT_CLOSED = 141  # the reader of the output went away (`| head`): 128 + SIGPIPE, as a shell
