"""Errors and the command-line entry of the LightFuse Blender scripts (bpy used as a Python module).

Every script reports a user error (bad file, unknown name, ...) with :class:`UserError`: one
line on stderr naming the file / field and what was expected, exit code 2, no traceback
(:func:`run_main`).
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings

import lfio

warnings.filterwarnings("ignore", category=DeprecationWarning)  # bpy 5.0 API notices


class UserError(Exception):
    """An error in the user's input: reported as one line, exit code 2."""


class Parser(argparse.ArgumentParser):
    """The scripts' argument parser: a bad command line is a :class:`UserError`."""

    def error(self, message):
        raise UserError(f"command line: {message}")


def run_main(main, argv=None) -> None:
    """Run ``main(argv)``; user errors -> one line on stderr and exit code 2."""
    try:
        main(argv)
    except UserError as e:
        sys.stdout.flush()
        print(f"error: {e}", file=sys.stderr)
        sys.stderr.flush()
        os._exit(2)  # bpy's atexit handlers can print noise; leave quietly
    except lfio.ExrError as e:
        sys.stdout.flush()
        print(f"error: {e}", file=sys.stderr)
        sys.stderr.flush()
        os._exit(2)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


class quiet_stdout:
    """Silence Blender's per-tile render log on fd 1 (C-level stdout) for a block."""

    def __enter__(self):
        sys.stdout.flush()
        self.saved = os.dup(1)
        self.null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(self.null, 1)

    def __exit__(self, *exc):
        sys.stdout.flush()
        os.dup2(self.saved, 1)
        os.close(self.saved)
        os.close(self.null)
        return False
