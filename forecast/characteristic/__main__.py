"""``python -m roomcap.forecast.characteristic train | eval`` (the same as ``forecast characteristic
...``)."""

from roomcap.forecast.lab.characteristic.cli import main

raise SystemExit(main())
