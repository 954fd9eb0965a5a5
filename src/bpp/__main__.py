"""``python -m bpp``: the ``bpp`` program."""

from bpp.launch import main

if __name__ == "__main__":
    main()
