from vfdata.cli import main

raise SystemExit(main())
