from warp_vision.sim.cli import main

main()
