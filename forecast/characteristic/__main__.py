"""``python -m forecast.characteristic train | eval`` (the same as ``forecast characteristic ...``)."""

from forecast.characteristic.cli import main

raise SystemExit(main())
