"""Placeholder so the workspace builds; its owner replaces this module."""


def main() -> None:
    raise SystemExit("not implemented yet")
