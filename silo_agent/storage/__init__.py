"""What the agent keeps on disk: the audit cache of scans and their results."""
