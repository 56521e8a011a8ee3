"""The results tables of README.md, results/README.md and docs/research-log.md, generated from
the committed records.

    python -m lab.table              # rewrite the tables between their marker comments
    python -m lab.table --check      # exit 1 with a diff if the committed text differs
    python -m lab.table --paired results/restaurant/pearl results/restaurant/mpc-sac

Every number comes from a record under results/: a run folder's `results.json` (test tasks after
two adaptation episodes, online, OOD), `curve.json` (budget, gradient steps, the last validation
point; `metrics.jsonl` and `config.json` where a run has no curve), its
`eval/policy-val-seeds1-8/results.json` (192 validation tasks, pooled) and
`eval/policy-scenarios-{test,ood}/results.json` (the paper's 25 test and 25 OOD scenarios); the
GP-MPC's from `results/gp_mpc/`; the speed figures from `benchmarks/results/`; the paper's from
`mpcpearl_jax.evaluation.report.PAPER`. A table lists its rows in `lab/tables/catalogue.py`
(or `summary.py`): a label and one run folder, or several folders of one configuration (one per
seed), shown as mean +- standard error over the seeds and the worst seed.
A missing record is reported by name (exit 1), never filled in.

`--paired A B` prints the paired difference A - B of the success rate over the 192 validation
tasks (the same tasks for both: the same task seeds, in the same order), with its standard error
over tasks and how many tasks each solved alone.
"""

from __future__ import annotations

import argparse
import difflib
import json
import re
import sys
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path

from lab.screen import render_screen, render_screen_learner
from lab.tables.render import (
    render_campaign_seeds,
    render_main_seed_summary,
    render_main_seeds,
    render_restaurant,
    render_robustness,
    render_robustness_choice,
    render_seed_curves,
    render_seeds,
    render_sidewalk_seeds,
)
from lab.tables.statistics import MISSING, VAL8, Records, paired_difference
from lab.tables.summary import (
    render_paper,
    render_robustness_summary,
    render_speed,
    render_summary,
)

LOG = "docs/research-log.md"
BLOCKS: tuple[tuple[str, str, Callable[[Records], str]], ...] = (  # file, block name, renderer
    ("README.md", "summary", render_summary),
    ("README.md", "speed", render_speed),
    ("results/README.md", "paper", render_paper),
    ("results/README.md", "seeds", render_seeds),
    ("results/README.md", "campaign-seeds", render_campaign_seeds),
    ("results/README.md", "robustness-summary", render_robustness_summary),
    ("results/README.md", "sidewalk-seeds", render_sidewalk_seeds),
    ("results/README.md", "speed", render_speed),
    (LOG, "seed-curves", render_seed_curves),
    (LOG, "restaurant", render_restaurant),
    (LOG, "main-seeds", render_main_seeds),
    (LOG, "main-seed-summary", render_main_seed_summary),
    (LOG, "robustness", render_robustness),
    (LOG, "robustness-choice", render_robustness_choice),
    (
        LOG,
        "screen-student-recipe",
        partial(render_screen, screen_file="lab/screens/student-recipe.json"),
    ),
    (
        LOG,
        "screen-methods-recipe",
        partial(render_screen, screen_file="lab/screens/methods-recipe.json"),
    ),
    (
        "docs/extensions.md",
        "screen-pipeline-recipe",
        partial(render_screen, screen_file="lab/screens/pipeline-recipe.json"),
    ),
    ("results/restaurant/screen/README.md", "screen-learner", render_screen_learner),
)
# the pages whose results/ paths must exist and whose generated blocks back README's figures
PAGES = ("README.md", "results/README.md", LOG)


def markers(name: str) -> tuple[str, str]:
    return f"<!-- table:{name} -->", f"<!-- /table:{name} -->"


def replace_block(text: str, name: str, body: str) -> str:
    """`text` with the lines between the block's two markers replaced by `body` (ValueError if
    the markers are not there exactly once each, in order)."""
    start, end = markers(name)
    if text.count(start) != 1 or text.count(end) != 1 or text.index(start) > text.index(end):
        raise ValueError(f"expected one {start} ... {end} block")
    head, rest = text.split(start, 1)
    _, tail = rest.split(end, 1)
    return f"{head}{start}\n{body}\n{end}{tail}"


Block = tuple[str, str, Callable[[Records], str]]  # (file under the root, block name, renderer)


def generate(
    results: Path, blocks: Sequence[Block] | None = None
) -> tuple[dict[Path, tuple[str, str]], list[str]]:
    """{page path: (committed text, generated text)} and the missing records; the pages are
    found under `results`' parent (README.md, results/README.md, docs/research-log.md)."""
    rec = Records(results)
    root = results.parent
    out: dict[Path, tuple[str, str]] = {}
    for rel, name, render in BLOCKS if blocks is None else blocks:
        path = root / rel
        old = out[path][1] if path in out else path.read_text()
        try:
            new = replace_block(old, name, render(rec))
        except ValueError as e:  # a marker deleted or doubled by hand
            raise ValueError(f"{rel}: {e}") from None
        out[path] = (out[path][0] if path in out else old, new)
    return out, rec.missing


# results/ paths as the READMEs write them: from the repository root, from results/, and run
# folders from results/restaurant/ ("ablation/...")
_REF_PREFIXES = ("results/", "restaurant/", "sidewalk/", "ablation/", "gp_mpc/", "earlier/")


def referenced_paths(text: str) -> list[str]:
    """The results/ paths a README names in `code`, [brackets] or link targets (outside fenced
    code blocks), except the folder after --out in a command."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    spans = re.findall(r"`([^`]+)`", text) + re.findall(r"\[([^\]\n]+)\]", text)
    spans += re.findall(r"\]\(([^)\s]+)\)", text)
    found: list[str] = []
    for span in spans:
        toks = span.replace(",", " ").replace("`", " ").split()
        for i, tok in enumerate(toks):
            tok = tok.rstrip(";:)")
            if i and toks[i - 1] == "--out" or any(c in tok for c in "<>*{}"):
                continue
            if tok.startswith(_REF_PREFIXES) and tok not in found:
                found.append(tok)
    return found


def missing_references(root: Path) -> list[str]:
    """'PAGE: path' for every results/ path the pages (`PAGES`) name that does not exist."""
    bases = (root, root / "results", root / "results" / "restaurant")
    out = []
    for rel in (page for page in PAGES if (root / page).is_file()):
        for ref in referenced_paths((root / rel).read_text()):
            if not any((b / ref).exists() for b in bases):
                out.append(f"{rel}: {ref}")
    return out


_BLOCK = re.compile(r"<!-- table:([\w-]+) -->\n(.*?)<!-- /table:\1 -->", re.S)
# a figure as the tables print one: two decimals (SR, CFR, SPL, TT, MGD, seed statistics)
_FIGURE = re.compile(r"(?<![\w.])(\d+\.\d\d)(?![\d])")


def unsourced_figures(root: Path) -> list[str]:
    """'README.md:LINE: X' for every figure (a number with two decimals, as the tables print them)
    that README.md's prose quotes (outside its generated blocks and code) and that neither a
    generated block of the pages (`PAGES`) nor the paper's table holds: a figure
    typed by hand that no record backs (e.g. an SR edited from 0.83 to 0.93). Python versions
    are not figures."""
    from mpcpearl_jax.evaluation.report import PAPER

    readme = (root / "README.md").read_text()
    generated = " ".join(
        body
        for rel in PAGES
        if (root / rel).is_file()
        for _, body in _BLOCK.findall((root / rel).read_text())
    )
    paper = {
        f"{v:.2f}"
        for rows in PAPER.values()
        for row in rows.values()
        if isinstance(row, dict)
        for v in row.values()
        if isinstance(v, float)
    }
    blank = lambda m: "\n" * m.group(0).count("\n")  # noqa: E731 (keep the line numbers)
    prose = _BLOCK.sub(blank, readme)
    prose = re.sub(r"^```.*?^```", blank, prose, flags=re.S | re.M)
    prose = re.sub(r"`[^`\n]*`", "", prose)
    out = []
    for n, line in enumerate(prose.splitlines(), 1):
        for m in _FIGURE.finditer(line):
            if line[: m.start()].endswith("Python "):
                continue
            if m.group(1) not in generated and m.group(1) not in paper:
                out.append(f"README.md:{n}: {m.group(1)}")
    return out


def _paired_record(arg: str) -> dict:
    p = Path(arg)
    if p.is_dir():
        p = p / VAL8
    if not p.is_file():
        raise FileNotFoundError(f"{arg}: no pooled validation record ({p})")
    return json.loads(p.read_text())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m lab.table",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("results", nargs="?", type=Path, default=Path("results"))
    ap.add_argument("--check", action="store_true", help="compare only; exit 1 on a difference")
    ap.add_argument("--paired", nargs=2, metavar=("A", "B"), help="run folders or pooled records")
    args = ap.parse_args(argv)
    if args.paired:
        try:
            a, b = (_paired_record(x) for x in args.paired)
            print(f"SR, A - B: {paired_difference(a, b)}")
        except (OSError, ValueError, KeyError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        return 0
    try:
        files, missing = generate(args.results)
    except (OSError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    changed = [(p, old, new) for p, (old, new) in files.items() if old != new]
    for p, old, new in changed:
        if args.check:
            sys.stdout.writelines(
                difflib.unified_diff(
                    old.splitlines(True), new.splitlines(True), f"{p} (committed)", f"{p} (records)"
                )
            )
        else:
            p.write_text(new)
            print(f"wrote {p}")
    for m in missing:
        print(f"missing record: {m}", file=sys.stderr)
    bad_refs = missing_references(args.results.parent) if args.check else []
    for ref in bad_refs:
        print(f"no such path: {ref}", file=sys.stderr)
    unsourced = unsourced_figures(args.results.parent) if args.check else []
    for fig in unsourced:
        print(f"a figure no record backs (not in a generated table): {fig}", file=sys.stderr)
    if missing:
        print(f"{len(missing)} record(s) missing: their cells read {MISSING}", file=sys.stderr)
    if args.check and changed:
        print("the tables differ from the records: run python -m lab.table", file=sys.stderr)
    return 1 if missing or bad_refs or unsourced or (args.check and changed) else 0


if __name__ == "__main__":
    raise SystemExit(main())
