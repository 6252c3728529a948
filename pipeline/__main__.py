"""The `pipeline` command (and `python -m pipeline`): pipeline.cli's click group, loaded here.

Loading the CLI imports dask, zarr and numpy (about half a second); a Ctrl-C then used to end
with a 30-line traceback from inside dask's or yaml's import, where a Ctrl-C a moment later
ends with one 'interrupted' line (pipeline.cli's _handle_errors). Now both end alike, exit code 130.
"""

import sys


def main() -> None:
    try:
        from pipeline.cli import main as cli
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)
    cli()


if __name__ == "__main__":
    main()
