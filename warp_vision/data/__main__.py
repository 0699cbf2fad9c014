from warp_vision.data.cli import main

raise SystemExit(main())
