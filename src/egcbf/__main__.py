"""``python -m egcbf``: the ``egcbf`` command."""

from .cli import main

if __name__ == "__main__":
    main()
