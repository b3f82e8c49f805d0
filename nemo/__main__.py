from nemo.cli import main

raise SystemExit(main())
