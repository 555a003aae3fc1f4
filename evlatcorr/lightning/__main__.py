"""Entry point of ``python -m evlatcorr.lightning``: large CPU pages asked for, then the command line."""

from evlatcorr.pages import prefer_large_pages

if __name__ == "__main__":
    prefer_large_pages()  # before lightning's import makes the process's first tensor
    from evlatcorr.lightning.cli import main

    main()
