from warp_vision.train.cli import main

raise SystemExit(main())
