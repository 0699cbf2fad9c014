from warp_vision.sim.cli import main

raise SystemExit(main())
