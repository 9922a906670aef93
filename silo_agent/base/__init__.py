"""Leaves every layer may use: atomic files, exit statuses, limits, the heap, the choices both
the config and the flags offer, logging. They import nothing of silo_agent."""
