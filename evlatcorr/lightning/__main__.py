"""Entry point of ``python -m evlatcorr.lightning``."""

from evlatcorr.lightning.cli import main

if __name__ == "__main__":
    main()
