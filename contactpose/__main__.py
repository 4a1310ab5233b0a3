from contactpose.cli import main

raise SystemExit(main())
