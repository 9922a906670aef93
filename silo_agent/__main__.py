from silo_agent.cli import entry

entry()
