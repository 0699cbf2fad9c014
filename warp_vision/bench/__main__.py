from warp_vision.bench.cli import main

raise SystemExit(main())
