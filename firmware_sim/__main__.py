"""``python -m firmware_sim``: the ECU command line (see `firmware_sim.cli`)."""
from firmware_sim.cli import main

raise SystemExit(main())
