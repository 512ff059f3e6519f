from clrecon.cli import main

raise SystemExit(main())
