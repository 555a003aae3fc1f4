"""Entry point of ``python -m evlatcorr.lightning``: CPU memory settings asked for, then the command line."""

from evlatcorr.pages import prefer_fast_memory

if __name__ == "__main__":
    prefer_fast_memory()  # before lightning's import makes the process's first tensor
    from evlatcorr.lightning.cli import main

    main()
