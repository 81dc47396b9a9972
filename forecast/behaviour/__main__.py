from forecast.behaviour.cli import main

raise SystemExit(main())
