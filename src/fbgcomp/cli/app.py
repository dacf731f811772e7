"""Command-line interface: a thin layer that parses, calls the library and prints.

The commands live in the modules of this package (:mod:`~fbgcomp.cli.offline`,
:mod:`~fbgcomp.cli.twin`, :mod:`~fbgcomp.cli.demo`, :mod:`~fbgcomp.cli.cnc_demo`,
:mod:`~fbgcomp.cli.scale`, :mod:`~fbgcomp.cli.runtime`); this module assembles them into the
``fbgcomp`` application, in the order ``fbgcomp --help`` lists them. The modules never import
this one.

Bad input raises :class:`fbgcomp.errors.InputError`; :func:`main` prints its one line on stderr
(``error: <file>, row R (line L), column C: ...``) and exits with code 2, without a traceback.
"""

from __future__ import annotations

import sys

import typer

from fbgcomp import progress
from fbgcomp.cli import cnc_demo, demo, offline, runtime, scale, twin
from fbgcomp.errors import InputError

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    help="fbgcomp: compensate machine-tool deformations from FBG sensors.",
)


@app.callback()
def _options(
    quiet: bool = typer.Option(
        False,
        "--quiet",
        "-q",
        help=(
            "No progress on stderr (also FBGCOMP_PROGRESS=0; FBGCOMP_PROGRESS=1 shows it even when stderr "
            "is not a terminal)."
        ),
    ),
):
    """fbgcomp: compensate machine-tool deformations from FBG sensors."""
    progress.QUIET = quiet


#: Every command, by name, in the order of ``fbgcomp --help``.
COMMANDS = (
    ("inspect", offline.inspect),
    ("fit", offline.fit),
    ("validate", offline.validate),
    ("simulate", offline.simulate),
    ("fe-calibrate", offline.fe_calibrate),
    ("resolution", twin.resolution),
    ("demo", demo.demo),
    ("compare", offline.compare),
    ("place", twin.place),
    ("plan", twin.plan),
    ("import", offline.import_campaign),
    ("report", offline.report),
    ("cnc-demo", cnc_demo.cnc_demo),
    ("ingest", scale.ingest),
    ("twin-check", twin.twin_check),
    ("serve", runtime.serve),
    ("sim-interrogator", runtime.sim_interrogator),
)

for _name, _command in COMMANDS:
    app.command(_name)(_command)
del _name, _command
app.add_typer(runtime.log_app, name="log")
app.add_typer(runtime.trust_app, name="trust")


def main(argv=None) -> int:
    """Run ``fbgcomp`` on ``argv`` (default: the process's arguments) and return the exit code:
    0 on success, 2 with one ``error: ...`` line for bad input, 130 when interrupted."""
    try:
        app(args=argv, prog_name="fbgcomp")
    except InputError as exc:
        print(f"error: {exc.one_line()}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        return 130
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    return 0
