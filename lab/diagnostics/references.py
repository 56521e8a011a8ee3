"""Which committed files under results/ anything names, and which figures and policy files
nothing does: `python -m lab.diagnostics.references [--unused]`.

A results/ path counts as named when it appears in a page (any .md outside results' run
folders), a table (`lab/tables/`: the catalogue's and the renderers' run folders), a
command or a test (`experiments/`, `lab/` and their campaign and
screen files, `tests/`, `benchmarks/`, `src/`). Paths are written from the
repository root (`results/restaurant/pearl`), from results/ (`restaurant/pearl`, in the pages
and tables) or from results/restaurant/ (`ablation/x`); a named folder names everything in it for
the policy files, a figure only counts as shown where its own file is named (or linked from a
page). `--unused` lists what a light checkout leaves out: trajectory figures and animated
episodes no page shows, and policy files (policy.msgpack, policy-trained.msgpack, network.json)
of runs nothing names. Records (results.json, curve.json, metrics.jsonl, config.json,
evaluations) are never listed.
"""

from __future__ import annotations

import argparse
import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "results"
# folders kept whole whatever names them
PROTECTED = ("results/restaurant/main-default/", "results/restaurant/screen/")
PROTECTED_GLOB = re.compile(r"^results/restaurant/main-seeds/default-s\d+/")
FIGURE = re.compile(r"(^|/)(trajectory_test\d+\.png|episode_test\d+\.gif|[a-z_]+_task\d+\.png)$")
POLICY = ("policy.msgpack", "policy-trained.msgpack", "network.json")
# a results/ path as written: from the root, from results/ or from results/restaurant/
_TOKEN = re.compile(
    r"(?:\.\./)*(?:results/)?(?:restaurant|sidewalk|gp_mpc|earlier|ablation|seeds|main-seeds|"
    r"paper-scenarios)/[\w.@{},*/-]*[\w*}]"
)
# link targets of a page, relative to the page
_LINK = re.compile(r"\]\(([^)\s]+)\)")


def tracked() -> list[str]:
    out = subprocess.run(
        ["git", "ls-files", "results"], cwd=ROOT, capture_output=True, text=True, check=True
    )
    return out.stdout.splitlines()


def sources() -> list[Path]:
    """The files whose text may name a results/ path."""
    out = subprocess.run(
        ["git", "ls-files", "*.md", "*.py", "*.json"], cwd=ROOT, capture_output=True, text=True
    )
    files = [ROOT / f for f in out.stdout.splitlines()]
    files += [ROOT / "docs/research-log.md"]  # also before it is committed
    keep = []
    for f in files:
        rel = f.relative_to(ROOT).as_posix()
        if not f.is_file() or rel in {str(k.relative_to(ROOT)) for k in keep}:
            continue
        if rel.startswith("results/") and not rel.endswith(".md"):
            continue  # records name their own folders; they are not pages, tables or commands
        keep.append(f)
    return keep


def _expand(token: str) -> list[str]:
    """A token with {a,b} braces as its alternatives (one level)."""
    m = re.search(r"\{([^{}]*)\}", token)
    if not m:
        return [token]
    return [token[: m.start()] + alt + token[m.end() :] for alt in m.group(1).split(",")]


def resolve(token: str, files: set[str], base: Path | None = None) -> list[str]:
    """Tracked results/ paths (files, or every file of a folder) a token names."""
    out: list[str] = []
    for tok in _expand(token.rstrip(".,;:")):
        tok = re.sub(r"^(\.\./)+", "", tok)
        cands = []
        if base is not None:
            p = (base / tok).resolve()
            if p.is_relative_to(ROOT):
                cands.append(p.relative_to(ROOT).as_posix())
        for prefix in ("", "results/", "results/restaurant/", "results/sidewalk/"):
            cands.append(prefix + tok)
        for c in cands:
            c = c.rstrip("/")
            if "*" in c:
                rx = re.compile("^" + re.escape(c).replace(r"\*", "[^/]*") + "$")
                hits = [f for f in files if rx.match(f)]
            elif c in files:
                hits = [c]
            else:
                hits = [f for f in files if f.startswith(c + "/")]
            if hits:
                out += hits
                break
    return out


def catalogue_runs() -> set[str]:
    """Run folders the generated tables read (lab/tables)."""
    from lab.tables import catalogue, summary

    runs: set[str] = set()

    def add(x: object) -> None:
        if isinstance(x, catalogue.Entry):
            runs.update(x.runs)
            runs.update(f for _, f in x.files)
        elif isinstance(x, str) and "/" in x:
            runs.add(x)
        elif isinstance(x, (tuple, list)):
            for y in x:
                add(y)
        elif isinstance(x, dict):
            for y in x.values():
                add(y)

    for mod in (catalogue, summary):
        for name in dir(mod):
            if name.isupper() or name.startswith("_") and name[1:].isupper():
                add(getattr(mod, name))
    for _, runs_ in catalogue.MAIN_SEEDS:
        runs.update(f"restaurant/{r}" for _, r in runs_)
    return {r for r in runs if not r.startswith("..")}


def named(files: list[str]) -> tuple[set[str], set[str]]:
    """(files named anywhere, figures a page shows or links)."""
    fs = set(files)
    hit: set[str] = set()
    shown: set[str] = set()
    for src in sources():
        text = src.read_text(errors="replace")
        base = src.parent
        for tok in _TOKEN.findall(text):
            paths = resolve(tok, fs, base)
            hit.update(paths)
            if src.suffix == ".md":
                shown.update(p for p in paths if FIGURE.search(p) and len(paths) == 1)
        if src.suffix == ".md":
            for link in _LINK.findall(text):
                paths = resolve(link, fs, base)
                hit.update(paths)
                shown.update(p for p in paths if FIGURE.search(p) and len(paths) == 1)
    for run in catalogue_runs():
        hit.update(resolve(run, fs))
    return hit, shown


def protected(path: str) -> bool:
    return path.startswith(PROTECTED) or bool(PROTECTED_GLOB.match(path))


def unused(files: list[str]) -> list[str]:
    """What a light checkout leaves out (see the module's docstring)."""
    hit, shown = named(files)
    out = []
    for f in files:
        if protected(f):
            continue
        if FIGURE.search(f) and f not in shown:
            out.append(f)
        elif Path(f).name in POLICY:
            run = str(Path(f).parent) + "/"
            if not any(h.startswith(run) and Path(h).name not in POLICY for h in hit):
                out.append(f)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m lab.diagnostics.references", description=__doc__)
    ap.add_argument(
        "--unused", action="store_true", help="list the figures and policy files nothing names"
    )
    args = ap.parse_args(argv)
    files = tracked()
    if args.unused:
        print("\n".join(unused(files)))
    else:
        hit, _ = named(files)
        print("\n".join(sorted(hit)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
