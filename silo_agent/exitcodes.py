"""Exit statuses of every silo-agent command, in one place (sysexits.h names where one fits),
so that scripts and systemd units can rely on them."""

EX_OK = 0
EX_FAILURE = 1  # the operation failed; the message on stderr says why
EX_USAGE = 2  # bad arguments (argparse's own status)
EX_DATAERR = 65  # bad input data: a scan directory, unmatched camera serials
EX_CONFIG = 78  # bad configuration file
EX_INTERRUPTED = 130  # Ctrl-C: 128 + SIGINT
