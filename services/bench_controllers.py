"""``racecav bench controllers`` (being written)."""
import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    pass


def run(args, cfg) -> int:
    print("not yet")
    return 1
