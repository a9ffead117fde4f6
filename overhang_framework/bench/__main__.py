from overhang_framework.bench.physics import main

raise SystemExit(main())
