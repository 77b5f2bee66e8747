from talkmesh.cli import main

raise SystemExit(main())
