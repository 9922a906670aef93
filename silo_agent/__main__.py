from silo_agent.cli import main

raise SystemExit(main())
