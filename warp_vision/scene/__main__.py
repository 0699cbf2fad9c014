from warp_vision.scene.cli import main

raise SystemExit(main())
