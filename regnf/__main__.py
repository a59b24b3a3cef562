from regnf.cli import main

raise SystemExit(main())
