from prismonet.cli import main

raise SystemExit(main())
