"""The `snac` command line. Each subcommand lives in its own module of this package, or in a
package that extends the library (`snac train` comes from `agents`, through the entry points of
`snac_jax.plugins`), and registers itself through `add_parser(subparsers)`; this module only
dispatches."""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from snac_jax import plugins

# One module per subcommand; each defines `add_parser(subparsers)`.
COMMAND_MODULES = ("rollout", "render", "eval", "play")
# CPU devices a subcommand gets without `--devices` (others: one per core). Training takes one:
# across devices the learner's minibatch shuffles become cross-device copies (bench/results/ppo.md).
CPU_DEVICES_BY_COMMAND = {"train": 1, "table": 1}


def build_parser() -> argparse.ArgumentParser:
    """The parser of every subcommand. An extension's command whose dependencies are not
    installed (its extra is missing) is still listed, and running it says which extra to add."""
    missing: dict[str, str] = {}
    while True:
        parser = argparse.ArgumentParser(prog="snac", description="SNAC mobile-construction benchmark in JAX")
        subparsers = parser.add_subparsers(dest="command", required=True)
        for name in COMMAND_MODULES:
            importlib.import_module(f"snac_jax.cli.{name}").add_parser(subparsers)
        for name, module in plugins.commands().items():
            if name in missing:
                _add_missing_extra_parser(subparsers, name, missing[name])
                continue
            try:
                importlib.import_module(module).add_parser(subparsers)
            except ModuleNotFoundError as error:
                if (message := plugins.missing_extra_message(error)) is None:
                    raise
                missing[name] = message
                break  # build again from scratch: the failed command may be half-registered
        else:
            return parser


def _add_missing_extra_parser(subparsers, name: str, message: str) -> None:
    """`snac NAME ...` that only says, in one line, which extra it needs (exit status 2)."""

    def refuse(args) -> int:
        raise ValueError(message)

    sub = subparsers.add_parser(name, add_help=False, help=message)
    sub.set_defaults(func=refuse, takes_any_arguments=True)


def use_cpu_devices_from(argv: list[str]) -> None:
    """Honour `--devices N` (default: `CPU_DEVICES_BY_COMMAND`, else one CPU device per core)
    before any subcommand module imports JAX: the CPU device count is fixed once JAX starts
    (see `snac_jax.devices`). A command that joins other processes (`--coordinator`) must start
    JAX itself, after `jax.distributed.initialize`, so here the count is only set."""
    from snac_jax import devices

    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--devices", default=None)
    pre.add_argument("--coordinator", default=None)
    known, _ = pre.parse_known_args(argv)
    if known.devices is None:
        count = CPU_DEVICES_BY_COMMAND.get(argv[0] if argv else None)
    else:
        try:
            count = int(known.devices)
        except ValueError:
            count = None  # the subcommand's own parser rejects it
    try:
        devices.use_cpu_devices(count if count is None or count >= 1 else None, start=known.coordinator is None)
    except RuntimeError:
        pass  # JAX already started in this process; the subcommand checks what it gets


def join_processes_from(argv: list[str]) -> None:
    """With `--coordinator HOST:PORT --num-processes N --process-id I`, join the other processes
    through `jax.distributed` now, before any module starts JAX (gymnax starts it on import); on
    CPUs their collectives go through gloo."""
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--coordinator", default=None)
    pre.add_argument("--num-processes", type=int, default=None)
    pre.add_argument("--process-id", type=int, default=None)
    known, _ = pre.parse_known_args(argv)
    if known.coordinator is None:
        if known.num_processes is not None or known.process_id is not None:
            raise SystemExit("snac: error: --num-processes and --process-id go with --coordinator HOST:PORT")
        return
    if known.num_processes is None or known.process_id is None:
        raise SystemExit("snac: error: --coordinator needs --num-processes N and --process-id I")
    if not (known.num_processes >= 1 and 0 <= known.process_id < known.num_processes):
        raise SystemExit(f"snac: error: --process-id must be in 0..{known.num_processes - 1}, got {known.process_id}")
    import jax

    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(
        coordinator_address=known.coordinator, num_processes=known.num_processes, process_id=known.process_id
    )


def main(argv: list[str] | None = None) -> int:
    """Run one subcommand. Bad input (`ValueError`), files that cannot be read or written
    (`OSError`) and a missing extra (`pip install "snac-jax[EXTRA]"`) end with one line,
    `snac CMD: error: ...`, and exit status 2; Ctrl-C with one
    line, `snac CMD: interrupted` (a subcommand may say more and return 130 itself), and exit
    status 130; anything else is a bug and keeps its traceback (as does every error with
    `SNAC_TRACEBACK=1`)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        return _main(argv)
    except KeyboardInterrupt:
        if os.environ.get("SNAC_TRACEBACK"):
            raise
        print(" ".join(["snac", *argv[:1]]) + ": interrupted", file=sys.stderr)
        return 130


def _main(argv: list[str]) -> int:
    use_cpu_devices_from(argv)
    join_processes_from(argv)
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if unknown and not getattr(args, "takes_any_arguments", False):
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    try:
        return args.func(args)
    except (ValueError, OSError, ModuleNotFoundError) as error:
        if os.environ.get("SNAC_TRACEBACK"):
            raise
        if isinstance(error, ModuleNotFoundError):
            # A dependency of an extra the command needs (say pygame for `snac play`); any
            # other missing module is a bug and keeps its traceback.
            if (message := plugins.missing_extra_message(error)) is None:
                raise
            error = ValueError(message)
        command = " ".join(part for part in (args.command, getattr(args, "algorithm", None)) if part)
        print(f"snac {command}: error: {_describe(error)}", file=sys.stderr)
        return 2


def _describe(error: BaseException) -> str:
    """One line for the user: the message, and for an OSError without one its kind and file."""
    if isinstance(error, OSError) and error.filename is not None and error.strerror:
        return f"{error.strerror}: {error.filename}"
    return str(error) or type(error).__name__


if __name__ == "__main__":
    sys.exit(main())
