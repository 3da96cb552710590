from sonarloc.cli import main

raise SystemExit(main())
