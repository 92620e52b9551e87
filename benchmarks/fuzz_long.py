"""The fuzzing of tests/test_fuzz.py for a time budget: configs, TOML text, structure files,
pair tables and pair-term arguments, with fresh random seeds and every registered plug-in type.

    PYTHONPATH=. python3 benchmarks/fuzz_long.py --seconds 600
    PYTHONPATH=. python3 benchmarks/fuzz_long.py --seconds 120 --targets structure,pair

It runs the targets in turn, a batch of examples at a time, until the budget is
spent (a batch that has started finishes, and hypothesis shrinks what it finds),
its address space capped by ``--memory-gb`` (a huge allocation is a finding),
then prints each distinct finding once, with its smallest failing example.
Exit code 0 when nothing was found, 1 otherwise, 3 when a case never returned
(stuck where no signal reaches it: it prints the case and its stack). A finding becomes a regression
test in tests/test_fuzz.py (an ``@example`` or a plain test) once it is fixed.
"""

from __future__ import annotations

import argparse
import faulthandler
import os
import random
import resource
import sys
import threading
import time
import traceback
from collections import Counter
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import seed as fixed_seed

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import test_fuzz as fuzz  # noqa: E402  (the strategies and checks live with the tests)


def _targets() -> dict:
    every = fuzz.every_type()
    return {
        "config": (
            fuzz.st.tuples(fuzz.mutated_configs(types=every), fuzz.FLAGS),
            lambda case: fuzz.check_config_text(fuzz.to_toml(case[0][1]), case[0][0], case[1]),
        ),
        "toml": (fuzz.garbled_texts(), lambda case: fuzz.check_config_text(case[1], case[0])),
        "structure": (fuzz.broken_structures(), lambda case: fuzz.check_structure(*case)),
        "table": (
            fuzz.st.builds(fuzz._pair_table).flatmap(fuzz.mutated_text),
            fuzz.check_table,
        ),
        "pair": (
            fuzz.pair_potential_arguments(),
            lambda arguments: fuzz.check_pair_potential(arguments, run=True),
        ),
    }


def _failures(error: BaseException) -> list[BaseException]:
    """The distinct failures hypothesis reports: one error, or an exception group of them."""
    if isinstance(error, BaseExceptionGroup):
        return [leaf for inner in error.exceptions for leaf in _failures(inner)]
    return [error]


def _describe(error: BaseException) -> tuple[str, str]:
    """(a key for telling findings apart, the text to print)."""
    message = str(error).strip()
    head = f"{type(error).__name__}: {message.splitlines()[0][:300] if message else ''}"
    notes = "\n".join(getattr(error, "__notes__", []))
    frames = traceback.extract_tb(error.__traceback__)
    where = next(
        (
            f"{f.filename}:{f.lineno}"
            for f in reversed(frames)
            if "/tests/" not in f.filename and "hypothesis" not in f.filename
        ),
        "",
    )
    return f"{type(error).__name__}|{where}|{head[:120]}", f"{head}\n  at {where}\n{notes}"


#: Seconds after which a case stuck where no signal reaches it (inside a C library) ends
#: the run: fuzz.time_limit's alarm, and the retry's, have had their turn.
WATCHDOG = 2 * fuzz.LIMIT + 60


def guarded(check, case):
    """``check(case)``, ending the process with the case and a traceback if it never returns."""

    def give_up():
        print(
            f"\nfuzz_long: finding: no return after {WATCHDOG:g} s, and no signal gets in "
            f"(a C library's loop?) while checking {case!r}; its stack:",
            flush=True,
        )
        faulthandler.dump_traceback(all_threads=True)  # the main thread is the one stuck
        os._exit(3)

    watchdog = threading.Timer(WATCHDOG, give_up)
    watchdog.daemon = True
    watchdog.start()
    try:
        return check(case)
    finally:
        watchdog.cancel()


def probe(strategy, check, examples: int, seed: int, current: list, outcomes: Counter):
    """Run ``check`` on ``examples`` draws of ``strategy``, counting what each returned
    (a run, a refusal) in ``outcomes``; return the failures."""

    def body(case):
        current[0] = case
        outcomes[guarded(check, case)] += 1

    test = settings(
        max_examples=examples,
        deadline=None,
        database=None,
        suppress_health_check=list(HealthCheck),
    )(given(case=strategy)(body))
    try:
        fixed_seed(seed)(test)()
    except KeyboardInterrupt:
        raise
    except BaseException as error:  # a failed check, or a hang (fuzz.Hang: not shrunk)
        failures = _failures(error)
        if isinstance(error, fuzz.Hang):
            case = current[0]
            error.add_note(f"while checking {case!r}")
            # Once more: kernels compiled on the way (slow on a loaded machine) are cached
            # now, so a case that was only slow passes; one that hangs hangs again.
            try:
                outcomes[guarded(check, case)] += 1
            except fuzz.Hang:
                return failures
            except Exception as again:  # a real finding behind the slowness
                again.add_note(f"while checking {case!r}")
                return [again]
            print(f"  (slow once, fine the second time: {case!r})", flush=True)
            return []
        return failures
    return []


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=600.0, help="time budget (default 600)")
    parser.add_argument(
        "--targets",
        default="config,toml,structure,table,pair",
        help="comma-separated: config, toml, structure, table, pair",
    )
    parser.add_argument("--batch", type=int, default=25, help="examples per batch (default 25)")
    parser.add_argument("--seed", type=int, default=None, help="first seed (default: random)")
    parser.add_argument(
        "--memory-gb",
        type=float,
        default=6.0,
        help="address space allowed to this process (default 6 GB): a case "
        "that allocates past it is a finding, not the machine's end",
    )
    args = parser.parse_args(argv)
    if args.memory_gb > 0:
        limit = int(args.memory_gb * 2**30)
        resource.setrlimit(resource.RLIMIT_AS, (limit, resource.getrlimit(resource.RLIMIT_AS)[1]))
    targets = _targets()
    chosen = [name.strip() for name in args.targets.split(",") if name.strip()]
    unknown = sorted(set(chosen) - set(targets))
    if unknown:
        parser.error(f"unknown target(s) {', '.join(unknown)}; choose from {', '.join(targets)}")
    seed = random.randrange(2**32) if args.seed is None else args.seed
    deadline = time.monotonic() + args.seconds
    findings: dict[str, tuple[str, str]] = {}
    outcomes = {name: Counter() for name in chosen}
    current = [None]
    round_ = 0
    print(f"fuzz_long: {args.seconds:g} s on {', '.join(chosen)}, first seed {seed}", flush=True)
    while time.monotonic() < deadline:
        name = chosen[round_ % len(chosen)]
        strategy, check = targets[name]
        batch_seed = seed + round_
        for error in probe(strategy, check, args.batch, batch_seed, current, outcomes[name]):
            key, text = _describe(error)
            if key not in findings:
                findings[key] = (name, text)
                print(f"\n[{name}] finding (seed {batch_seed}):\n{text}", flush=True)
        round_ += 1
    print(
        f"\nfuzz_long: {round_} batches, {len(findings)} distinct finding(s); outcomes "
        "(with hypothesis's shrinking runs):"
    )
    for name, counter in outcomes.items():
        print(f"  {name}: " + ", ".join(f"{what} {n}" for what, n in counter.most_common()))
    for name, text in findings.values():
        print(f"- [{name}] {text.splitlines()[0]}")
    return 1 if findings else 0


if __name__ == "__main__":
    sys.exit(main())
