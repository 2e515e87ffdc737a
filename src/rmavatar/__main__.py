from rmavatar.commands import main

raise SystemExit(main())
