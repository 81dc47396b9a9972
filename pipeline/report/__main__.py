"""``python -m roomcap.pipeline.report SESSION [--overlay]``: the report of a session folder."""

import sys

from roomcap.pipeline.report.page import main

if __name__ == "__main__":
    sys.exit(main())
