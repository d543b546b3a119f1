import sys

from _diffrax_vi_cli import command


if __name__ == "__main__":
    sys.exit(command())
