"""``uwbimu demo``: the main job on built-in defaults."""

from __future__ import annotations

import typer


def register(app: typer.Typer) -> None:
    @app.command("demo")
    def demo() -> None:
        """Simulate a default calibration flight, validate it, estimate and report."""
        raise typer.Exit(code=1)
