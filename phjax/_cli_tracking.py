"""Tracking commands of the CLI (placeholder registration; filled in below)."""


def add_commands(sub) -> None:  # pragma: no cover - replaced in the same change
    return None
