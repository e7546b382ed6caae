from smartedge.cli import main

raise SystemExit(main())
