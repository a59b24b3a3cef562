from regnf.cli.app import main

raise SystemExit(main())
