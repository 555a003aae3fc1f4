"""The paper's Table 1 on simulated data, as a Lightning test loop (``evlatcorr.benchmark.table1``).

    python benchmarks/run.py                 # 3 unseen test scenes, 256x336, 20 ms exposure, 4 ms latency
    python benchmarks/run.py --scenes 8      # all 8 test photographs (about 20 minutes on 2 CPU cores)
    python benchmarks/run.py --quick         # CI-sized run (2 small scenes)
    python benchmarks/run.py --help          # every option
"""

import _setup  # noqa: F401  first: the repository on sys.path and 2 MB CPU pages, before torch loads

# isort: split

import sys

from evlatcorr.benchmark.table1 import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
