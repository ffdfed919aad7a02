from dicer.cli import main

raise SystemExit(main())
