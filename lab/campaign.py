"""A queue of training runs, trained one at a time and resumable across sessions.

    python -m lab.campaign CAMPAIGN.json [--only NAME ...] [--dry-run]

A campaign file lists training runs on a time budget (`python -m experiments.restaurant
--minutes M`, with its learning curve; `--env sidewalk` for the sidewalk) and what to do with
each when it has finished:

    {"runs": [{"name": "mpc-pearl-s0",
               "argv": ["--preset", "cpu-explore", "--eps", "0.2", "--seed", "0",
                        "--minutes", "24", "--eval-minutes", "3"],
               "results": "results/restaurant/seeds/mpc-pearl-eps0.2-s0",
               "evaluate": [["--split", "val", "--task-seeds", "1-8", "--figures", "none",
                             "--out", "{results}/eval/policy-val-seeds1-8"]]},
              ...]}

A run may name `"trainer": "grbal"` to train with `python -m experiments.grbal` (the GrBAL
baseline; `--minutes` is its budget) or `"trainer": "restaurant"` to train with the main command
`python -m experiments.restaurant` with a budget in iterations (its record: results.json)
instead of a time budget (its record: curve.json).

For each run in order: a run whose results folder holds its finished record (curve.json
for a time budget; results.json for the other two) is done and skipped; a run whose training ended
(exit 0; the campaign then writes `campaign.json` into its work folder `runs/campaign/<name>`) is
copied into its results folder without checkpoints and then evaluated; a run with checkpoints is
resumed (`--resume`; GrBAL's time budget then starts again in the resumed process); any other is
started afresh (a work folder a run killed before its first checkpoint left is cleared first).
Before a finished run is copied or evaluated, the config its `argv` builds is compared with the
config.json the run recorded: an entry edited since is refused with the fields that differ (give
the changed entry another name and results folder). An evaluation is given as the flags of the
evaluation command (`python -m experiments.evaluate RESULTS ARGS...`); when the file is loaded,
they are read, by that command's parser, as `mpcpearl_jax.evaluate`'s keyword arguments on the
copied folder, and each evaluation runs them in a process of its own (`python -m lab.evaluation`
with the keyword arguments as one JSON object, `lab/evaluation.py`), as the trainings do: the
campaign itself never loads a model, an evaluation's memory goes with its process, and a crash
in one stops the campaign with its exit code instead of taking the campaign down. An evaluation
must name its `--out` (`{results}` stands for the results folder) and is skipped where that
folder holds results.json. One training or evaluation at a time, each in its own process: stop
the campaign with Ctrl-C (the process under way saves or stops, and exits 130) and start the
same command again later to continue where it stopped.
A run that fails (exit code other than 0) stops the campaign with its name and code. SIGTERM or
SIGHUP to the campaign (`timeout`, a scheduler, a closed terminal) reaches the run under way as
Ctrl-C (it saves and exits), and the campaign ends once it has; a campaign killed outright
(SIGKILL) takes its run with it (the run gets SIGINT from the kernel), so no training outlives
its campaign. One campaign file is processed by one campaign at a time (a lock in
runs/campaign/); every entry is checked (keys, names, results paths) before anything runs.

Before a training with a wall-clock budget (--minutes, and GrBAL) starts, the campaign waits
until the 1-minute load average is below the warning level of a time budget (at most
SETTLE_MAX_S), so that the previous run's evaluations, which keep it up for a minute after
they end, neither eat into the new run's budget nor mark its record as trained beside another job.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Collection
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lab import evaluation

WORK = Path("runs") / "campaign"
NOT_COPIED = ("checkpoints", ".lock")
TRAINED = "campaign.json"  # written into the work folder once its training exited 0
KEYS = ("name", "argv", "results", "evaluate", "trainer")  # what an entry may hold
SETTLE_LOAD = 1.5  # = mpcpearl_jax.training.budget.LOAD_WARN
SETTLE_MAX_S = 120.0


# trainer -> (module, the file that marks a finished run, whether its budget is wall-clock time)
TRAINERS = {
    "learning": ("experiments.restaurant", "curve.json", True),  # --minutes: a learning curve
    "grbal": ("experiments.grbal", "results.json", True),
    "restaurant": ("experiments.restaurant", "results.json", False),
}


@dataclass(frozen=True)
class CampaignEvaluation:
    """One evaluation of a campaign entry: `mpcpearl_jax.evaluate`'s keyword arguments (the run
    folder under "run") as the JSON object its process is given (`lab.evaluation`)."""

    keywords: str

    @classmethod
    def of(cls, results: Path, args: tuple[str, ...]) -> CampaignEvaluation:
        """The evaluation the command's flags `args` give on the results folder `results`;
        ValueError with the command's message (module doc)."""
        return cls(json.dumps(evaluation.keywords(results, args)))

    @property
    def arguments(self) -> dict[str, Any]:
        return json.loads(self.keywords)

    @property
    def record(self) -> Path:
        """The results.json it writes."""
        return evaluation.record(self.arguments)

    @property
    def command(self) -> list[str]:
        return evaluation.command(self.arguments)


@dataclass(frozen=True)
class CampaignRun:
    name: str
    argv: tuple[str, ...]
    results: Path
    evaluate: tuple[CampaignEvaluation, ...] = field(default_factory=tuple)
    trainer: str = "learning"

    @property
    def work(self) -> Path:
        return WORK / self.name

    @property
    def module(self) -> str:
        return TRAINERS[self.trainer][0]

    @property
    def record(self) -> str:
        return TRAINERS[self.trainer][1]

    @property
    def time_budget(self) -> bool:
        """The main command's run on a time budget: a learning run, or a `restaurant` entry given
        --minutes (it records the iterations it managed as `train.iterations`)."""
        return self.trainer == "learning" or (
            self.trainer == "restaurant" and any(a.split("=")[0] == "--minutes" for a in self.argv)
        )

    @property
    def wall_clock(self) -> bool:
        """Its training has a wall-clock budget (--minutes, and GrBAL): it waits for the load."""
        return TRAINERS[self.trainer][2] or self.time_budget


def load_campaign(path: Path) -> list[CampaignRun]:
    """The runs of a campaign file; ValueError naming the file and the bad entry."""
    try:
        raw = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: not a readable JSON campaign ({e})") from e
    runs = raw.get("runs") if isinstance(raw, dict) else None
    if not isinstance(runs, list) or not runs:
        raise ValueError(f"{path}: expected {{'runs': [...]}} with at least one run")
    extra = sorted(set(raw) - {"runs"})
    if extra:
        raise ValueError(f"{path}: unknown key(s) {extra}; a campaign file holds 'runs' only")
    out: list[CampaignRun] = []
    names: set[str] = set()
    for i, r in enumerate(runs):
        run = parse_entry(r, f"{path}: runs[{i}]", names)
        names.add(run.name)
        out.append(run)
    return out


def parse_entry(r: object, where: str, names: Collection[str] = ()) -> CampaignRun:
    """One campaign entry (a dict as a campaign file holds it) checked and built; ValueError
    starting with `where` (the file and the entry) on a bad one. `names`: the names taken."""
    if not isinstance(r, dict) or not {"name", "argv", "results"} <= set(r):
        raise ValueError(f"{where}: needs 'name', 'argv' and 'results'")
    unknown = sorted(set(r) - set(KEYS))
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown}; an entry holds {list(KEYS)}")
    name = r["name"]
    if (
        not isinstance(name, str)
        or not name
        or name.startswith(".")
        or any(c in name for c in "/\\")
        or name in names
    ):
        raise ValueError(
            f"{where}: 'name' must be a unique folder name (no '/', not starting with "
            f"'.'), got {name!r}"
        )
    if not isinstance(r["results"], str) or not r["results"].strip():
        raise ValueError(f"{where}: 'results' must be a folder path (a string)")
    _check_results_path(Path(r["results"]), where)
    argv = r["argv"]
    if not isinstance(argv, list) or not all(isinstance(a, str) for a in argv):
        raise ValueError(f"{where}: 'argv' must be a list of strings")
    for flag in ("--out", "--resume", "--overwrite"):
        if flag in argv:
            raise ValueError(f"{where}: 'argv' must not hold {flag} (the campaign sets it)")
    evals = r.get("evaluate", [])
    if not isinstance(evals, list) or not all(
        isinstance(e, list) and all(isinstance(a, str) for a in e) for e in evals
    ):
        raise ValueError(f"{where}: 'evaluate' must be a list of argument lists")
    trainer = r.get("trainer", "learning")
    if trainer not in TRAINERS:
        raise ValueError(f"{where}: 'trainer' must be one of {sorted(TRAINERS)}")
    results = Path(r["results"])
    evaluations = []
    for e in evals:
        args = tuple(a.replace("{results}", str(results)) for a in e)
        if "--out" not in args[:-1]:
            raise ValueError(f"{where}: every 'evaluate' entry must give --out")
        try:  # read by the evaluation command's parser, before anything runs
            ev = CampaignEvaluation.of(results, args)
        except ValueError as err:
            raise ValueError(f"{where}: 'evaluate' {' '.join(args)}: {err}") from None
        _check_results_path(ev.record.parent, where, "'evaluate' --out")
        evaluations.append(ev)
    return CampaignRun(name, tuple(argv), results, tuple(evaluations), trainer)


def _check_results_path(results: Path, where: str, field: str = "'results'") -> None:
    """ValueError naming the entry and its field when a folder it writes cannot be made: a file
    on its path, or an existing folder on it that this user cannot write."""
    what = f"{where}: {field}"
    for parent in (results, *results.parents):
        if parent.exists():
            if not parent.is_dir():
                raise ValueError(f"{what} {results}: {parent} is a file")
            if not os.access(parent, os.W_OK | os.X_OK):
                raise ValueError(f"{what} {results}: {parent} is not writable")
            return


def _has_checkpoint(run: CampaignRun) -> bool:
    ckpts = run.work / "checkpoints"
    return ckpts.is_dir() and any(p.name.isdigit() for p in ckpts.iterdir())


def state_of(run: CampaignRun) -> str:
    """'done', 'finished' (trained, not yet copied), 'resume', or 'new'. A run is finished once
    its training process exited 0 (the campaign's mark, `TRAINED`); a process killed after its
    record but before its last file is resumed, so that it writes them all again."""
    if (run.results / run.record).is_file():
        return "done"
    if (run.work / TRAINED).is_file() and (run.work / run.record).is_file():
        return "finished"
    if _has_checkpoint(run):
        return "resume"
    return "new"


def _holds_another_run(run: CampaignRun) -> bool:
    """Whether the results folder holds a run's records that this entry did not copy there (a
    copy of this entry's run carries its campaign.json)."""
    from mpcpearl_jax.training.run import run_records

    if not run.results.is_dir() or not run_records(run.results):
        return False
    try:
        return json.loads((run.results / TRAINED).read_text()).get("name") != run.name
    except (OSError, json.JSONDecodeError, AttributeError):
        return True


def built_config(run: CampaignRun):
    """The config the entry's argv builds now (as its trainer's command line would)."""
    from mpcpearl_jax.cli.args import config_from_argv

    try:
        return config_from_argv(run.trainer, list(run.argv))
    except SystemExit as e:  # argparse's own error, printed above
        raise ValueError(f"{run.name}: its argv is not a valid {run.module} command line") from e


def check_unchanged(run: CampaignRun, folder: Path) -> None:
    """ValueError naming the entry and the fields when the config its argv builds differs from
    the one the run in `folder` recorded (config.json): the entry was edited after training."""
    from mpcpearl_jax.errors import ConfigError
    from mpcpearl_jax.training.checkpoint import config_differences

    recorded = folder / "config.json"
    if not recorded.is_file():
        return
    try:
        now = built_config(run)
        if run.trainer == "grbal":
            from mpcpearl_jax.grbal.config import GrbalExperimentConfig as Config
        else:
            from mpcpearl_jax.config import ExperimentConfig as Config  # type: ignore[assignment]
        then = Config.from_dict(json.loads(recorded.read_text()))
    except (ConfigError, TypeError, ValueError) as e:
        raise ValueError(f"{run.name}: cannot compare its argv with {recorded}: {e}") from e
    # a run on a time budget records the iterations it did; where a run computed never matters
    # (`config.RESULT_NEUTRAL`: devices, the MPC's worker processes)
    from mpcpearl_jax.config import RESULT_NEUTRAL

    ignore = (*RESULT_NEUTRAL, "train.iterations") if run.time_budget else RESULT_NEUTRAL
    diff = config_differences(then, now, ignore)
    if diff:
        raise ValueError(
            f"{run.name}: its argv builds a config that differs from the trained run's "
            f"{recorded} in {diff}; restore the entry, or give the changed one another name and "
            "results folder"
        )


def copy_results(run: CampaignRun) -> None:
    """The finished work folder into the results folder, without checkpoints (the finished
    record last, so that a copy cut short is not taken for a finished one)."""
    run.results.mkdir(parents=True, exist_ok=True)
    for p in sorted(run.work.iterdir(), key=lambda p: p.name == run.record):
        if p.name in NOT_COPIED:
            continue
        dest = run.results / p.name
        if p.is_dir():
            shutil.copytree(p, dest, dirs_exist_ok=True)
        else:
            shutil.copy2(p, dest)


def commands(run: CampaignRun, state: str) -> list[list[str]]:
    """The processes still to run for `run` in `state` (see module doc)."""
    py = [sys.executable, "-m"]
    cmds: list[list[str]] = []
    if state in ("new", "resume"):
        extra = ["--resume"] if state == "resume" else []
        cmds.append(py + [run.module, *run.argv, "--out", str(run.work), *extra])
    cmds += [ev.command for ev in run.evaluate if not ev.record.is_file()]
    return cmds


def settle(limit_s: float = SETTLE_MAX_S, poll_s: float = 5.0) -> float:
    """Wait until the 1-minute load average is below SETTLE_LOAD, at most `limit_s` seconds;
    the seconds waited."""
    if not hasattr(os, "getloadavg"):
        return 0.0
    waited = 0.0
    while os.getloadavg()[0] >= SETTLE_LOAD and waited < limit_s:
        time.sleep(poll_s)
        waited += poll_s
    return waited


def run_child(cmd: list[str]) -> int:
    """Run one process to its end and return its exit code. The child runs in a session of its
    own, and every SIGINT the campaign gets (Ctrl-C in its terminal, or `kill -INT` of the
    campaign's process alone, e.g. under nohup) is passed on to it once: the child saves and
    exits (130) while the campaign keeps waiting, instead of being killed as `subprocess.call`
    does after a quarter of a second; a second Ctrl-C reaches it as a second one (stop at once).
    SIGINT is handled even where the campaign started with it ignored, as a shell without job
    control starts a background job (`nohup ... &` in a script)."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    ended: list[int] = []

    def terminate(signum, frame):  # SIGTERM / SIGHUP: stop the child as Ctrl-C would
        ended.append(signum)
        raise KeyboardInterrupt

    old = {s: signal.signal(s, terminate) for s in (signal.SIGTERM, signal.SIGHUP)}
    try:
        p = subprocess.Popen(_dies_with_parent(cmd), start_new_session=True)
        while True:
            try:
                rc = p.wait()
                return 128 + ended[0] if ended else rc
            except KeyboardInterrupt:
                if p.poll() is None:
                    p.send_signal(signal.SIGINT)
    finally:
        for s, handler in old.items():
            signal.signal(s, handler)


# the child's first act, before it becomes `cmd`: SIGINT when its parent (this campaign) dies,
# kept across exec (Linux prctl PR_SET_PDEATHSIG = 1); exit at once if the parent is gone already
_GUARD = (
    "import ctypes, os, signal, sys\n"
    "parent = int(sys.argv[1])\n"
    "try:\n"
    "    ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGINT), 0, 0, 0)\n"
    "except (OSError, AttributeError):\n"
    "    pass\n"
    "if os.getppid() != parent:\n"
    "    sys.exit(130)\n"
    "os.execv(sys.argv[2], sys.argv[2:])\n"
)


def _dies_with_parent(cmd: list[str]) -> list[str]:
    """`cmd` started through a guard that makes the kernel send it SIGINT (save and exit) when
    the campaign dies, even by SIGKILL (Linux; elsewhere `cmd` as it is)."""
    if not sys.platform.startswith("linux"):
        return cmd
    return [sys.executable, "-c", _GUARD, str(os.getpid()), *cmd]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("campaign", type=Path)
    p.add_argument("--only", nargs="*", default=None, help="these run names only")
    p.add_argument("--dry-run", action="store_true", help="print what would run, run nothing")
    args = p.parse_args(argv)
    try:
        runs = load_campaign(args.campaign)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.only is not None:
        unknown = sorted(set(args.only) - {r.name for r in runs})
        if unknown:
            print(f"error: --only: no run named {unknown} in {args.campaign}", file=sys.stderr)
            return 2
        runs = [r for r in runs if r.name in args.only]
    # one campaign per campaign file at a time
    lock = WORK / f".{args.campaign.resolve().name}.campaign"
    return run_all(runs, lock, args.dry_run, source=str(args.campaign))


def run_all(runs: list[CampaignRun], lock: Path, dry_run: bool = False, source: str = "") -> int:
    """Train, copy and evaluate `runs` in order, one process at a time, as the campaign does
    (module doc), holding the lock folder `lock` throughout: a second caller with the same lock
    gets exit 2 and an error naming `source` (the file the runs came from). `dry_run` prints the
    processes and runs nothing (and takes no lock). The first failing process's exit code, or 0."""
    if dry_run:
        return _process(runs, dry_run=True)
    from mpcpearl_jax.errors import RunDirError
    from mpcpearl_jax.training.runlock import RunLock

    try:
        held = RunLock(lock)
    except RunDirError as e:
        print(f"error: {source or lock}: another campaign is running it ({e})", file=sys.stderr)
        return 2
    try:
        return _process(runs, dry_run=False)
    finally:
        held.release()


def _process(runs: list[CampaignRun], dry_run: bool) -> int:
    for run in runs:
        state = state_of(run)
        if state == "done" and not run.evaluate:
            print(f"[campaign] {run.name}: done", flush=True)
            continue
        todo = commands(run, "done" if state in ("done", "finished") else state)
        if state in ("done", "finished") and todo:  # about to copy or evaluate a trained run
            try:
                check_unchanged(run, run.results if state == "done" else run.work)
            except ValueError as e:
                print(f"error: {e}", file=sys.stderr)
                return 2
        if state != "done" and _holds_another_run(run):
            print(
                f"error: {run.name}: its results folder {run.results} holds another run's "
                "records; give the entry another 'results' folder",
                file=sys.stderr,
            )
            return 2
        if state == "finished" and not dry_run:
            copy_results(run)  # trained earlier: the evaluations read the results folder
        if state == "new" and run.work.exists() and not dry_run:
            shutil.rmtree(run.work)  # killed before its first checkpoint: start afresh
        print(f"[campaign] {run.name}: {state}, {len(todo)} process(es) to run", flush=True)
        for i, cmd in enumerate(todo):
            print("[campaign] $ " + shlex.join(cmd[1:]), flush=True)
            if dry_run:
                continue
            if i == 0 and state in ("new", "resume") and run.wall_clock:
                waited = settle()
                if waited:
                    load = os.getloadavg()[0]
                    print(
                        f"[campaign] waited {waited:.0f} s for the load average (now {load:.2f})",
                        flush=True,
                    )
            rc = run_child(cmd)
            if rc != 0:
                print(f"error: {run.name}: {cmd[2]} exited {rc}", file=sys.stderr)
                return rc
            if i == 0 and state in ("new", "resume"):
                mark = {"name": run.name, "trainer": run.trainer, "argv": list(run.argv)}
                run.work.mkdir(parents=True, exist_ok=True)
                (run.work / TRAINED).write_text(json.dumps(mark, indent=1) + "\n")
                copy_results(run)  # trained: the evaluations read the results folder
    return 0


if __name__ == "__main__":
    sys.exit(main())
