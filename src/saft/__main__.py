from saft.cli import main

raise SystemExit(main())
