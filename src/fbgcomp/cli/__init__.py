"""Command-line interface: all Typer wiring lives here and nowhere else."""
