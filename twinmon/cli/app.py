"""The ``twinmon`` click group: global options, and twinmon errors turned into one stderr line
and a per-family exit code. The command modules attach their commands to :func:`main`."""
from __future__ import annotations

import signal

import click

from .. import __version__, interrupts
from ..errors import Interrupted, TwinmonError

#: Set when SIGTERM arrived: the command ends as after a Ctrl-C, with 143 instead of 130.
_terminated = False


def _on_sigterm(signum, frame) -> None:
    """SIGTERM (``kill``, ``timeout``, make's or a batch scheduler's time limit) ends a command
    the way Ctrl-C does: through the SIGINT handler in force (a stage's interrupt guard, or
    Python's KeyboardInterrupt), so pools are stopped, temporaries and locks removed and a
    resumable partial file kept. Python's default for SIGTERM is to die on the spot, which
    leaves the workers' scratch folder and the output's lock behind."""
    global _terminated
    _terminated = True
    handler = signal.getsignal(signal.SIGINT)
    if callable(handler):
        handler(signal.SIGINT, frame)
    else:                       # SIG_IGN or SIG_DFL: nobody catches SIGINT in this process
        raise KeyboardInterrupt


def _terminated_exit(ctx) -> None:
    ctx.exit(128 + signal.SIGTERM)


class TwinmonGroup(click.Group):
    """Turns twinmon errors into one stderr line and a per-family exit code."""

    def invoke(self, ctx):
        try:
            out = super().invoke(ctx)
            # A Ctrl-C swallowed on its way (interrupts.py) still ends the command as one.
            interrupts.raise_if_interrupted()
            return out
        except TwinmonError as exc:
            if ctx.obj and ctx.obj.get("verbose"):
                import traceback
                traceback.print_exc()
            if _terminated and isinstance(exc, Interrupted):
                # The stage's own words (what is kept), the shell's code for SIGTERM.
                click.echo(f"twinmon: terminated: {exc.message}", err=True)
                _terminated_exit(ctx)
            click.echo(f"twinmon: {exc.family}: {exc.message}", err=True)
            ctx.exit(exc.exit_code)
        except RuntimeError as exc:
            # OpenTURNS catches a Ctrl-C that arrives inside its C++ with a handler of its
            # own, and raises "Interruption in OT::..." (our handler never sees it).
            if not (interrupts.pending() or str(exc).startswith("Interruption in OT::")):
                raise
            click.echo("twinmon: interrupted", err=True)
            ctx.exit(143 if _terminated else 130)
        except KeyboardInterrupt:
            # Ctrl-C: one line and the shell's code for SIGINT; stages that resume say so
            # themselves (Interrupted above).
            if _terminated:
                click.echo("twinmon: terminated", err=True)
                _terminated_exit(ctx)
            click.echo("twinmon: interrupted", err=True)
            ctx.exit(130)
        except OSError as exc:
            # A file system problem (permissions, full disk) that no stage anticipated: still one
            # line naming the file, with its own exit code.
            if ctx.obj and ctx.obj.get("verbose"):
                import traceback
                traceback.print_exc()
            where = f"{exc.filename}: " if exc.filename else ""
            # HDF5's errors span several lines of internals: the first says what happened.
            what = exc.strerror or (str(exc).splitlines() or [type(exc).__name__])[0]
            click.echo(f"twinmon: I/O error: {where}{what}", err=True)
            ctx.exit(8)


@click.group(cls=TwinmonGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="twinmon")
@click.option("-v", "--verbose", is_flag=True, help="Show tracebacks and details.")
@click.option("-q", "--quiet", is_flag=True, help="No progress bars or human summaries.")
@click.pass_context
def main(ctx, verbose, quiet):
    """Health monitoring of machines through calibrated digital twins.

    Exit codes: 0 ok, 2 usage, 3 config, 4 input data, 5 artifact, 6 simulation,
    7 calibration, 8 I/O (or output busy), 130 interrupted, 143 terminated (SIGTERM).
    """
    global _terminated
    _terminated = False         # a process that runs several commands: this one's SIGTERM only
    interrupts.reset()
    old_int = interrupts.install()
    if old_int is not None:
        ctx.call_on_close(lambda: signal.signal(signal.SIGINT, old_int))
    try:
        old = signal.signal(signal.SIGTERM, _on_sigterm)
    except ValueError:          # not the main thread (an embedding application's worker)
        old = None
    if old is not None:
        # Put the caller's handler back: main() may run inside a longer-lived process.
        ctx.call_on_close(lambda: signal.signal(signal.SIGTERM, old))
    ctx.ensure_object(dict)
    ctx.obj["verbose"] = verbose
    ctx.obj["quiet"] = quiet
