"""(placeholder, being written) vgripd calibrate import-mct / export-mct."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser, name: str) -> None:
    pass


def run(args: argparse.Namespace) -> int:
    raise NotImplementedError
