from rmavatar.cli import main

raise SystemExit(main())
