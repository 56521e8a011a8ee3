"""Which records make which rows: the tables' entries (a label and one run folder, or one
folder per seed of the same configuration), the seed groups, evaluation sets and perturbations,
and the paper's ordering claims. Data only: reading and rendering live beside it."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Entry:
    """One row (or column) of a table.

    runs: run folders under results/, one per seed of the same configuration; files: for a
    controller without a run folder (the GP-MPC), kind -> record file under results/; paper: a
    method of `PAPER["restaurant"]`; absent: kinds that have no record by design, shown as '-'.
    Kinds: test, online, ood (results.json), budget, grad_steps, val_end (curve.json), val8,
    scen_test, scen_ood (eval records).
    """

    label: str
    runs: tuple[str, ...] = ()
    files: tuple[tuple[str, str], ...] = ()
    paper: str | None = None
    absent: frozenset[str] = frozenset()

    def sources(self) -> list[str]:
        return list(self.runs) + [f for _, f in self.files]


_GP_MPC = Entry(
    "GP-MPC (this project)",
    files=(
        ("test", "gp_mpc/restaurant_test.json"),
        ("val8", "gp_mpc/restaurant_val_seeds1-8.json"),
        ("scen_test", "gp_mpc/scenarios/restaurant_test.json"),
        ("scen_ood", "gp_mpc/scenarios/restaurant_ood.json"),
    ),
)
GP_MPC = _GP_MPC  # the GP-MPC's records with 2 QPs, without the unsafe-plan recovery
# the GP-MPC of the `paper` preset's expert, the SQP to convergence (`python -m experiments.gp_mpc`
# with the MPCConfig defaults): README's summary and the paper's table side by side
GP_MPC_CONVERGED = Entry(
    "GP-MPC (this project, the SQP to convergence)",
    files=(
        ("scen_test", "gp_mpc/converged/scenarios/restaurant_test.json"),
        ("scen_ood", "gp_mpc/converged/scenarios/restaurant_ood.json"),
    ),
    absent=frozenset({"test", "val8"}),
)
# the GP-MPC of the learned presets' expert, 2 QPs with the unsafe-plan recovery (`python -m
# experiments.gp_mpc --scenarios DIR --split test --preset default`): README's summary and the
# paper's table side by side
GP_MPC_EXPERT = Entry(
    "GP-MPC (this project, the learned presets' expert)",
    files=(("scen_test", "gp_mpc/teacher/scenarios/restaurant_test.json"),),
    absent=frozenset({"test", "val8", "scen_ood"}),
)
_GP_MPC_TEACHER = Entry(
    "GP-MPC with unsafe-plan recovery (the learned agents' MPC)",
    files=(
        ("test", "gp_mpc/restaurant_test_unsafe-recovery.json"),
        ("val8", "gp_mpc/restaurant_val_seeds1-8_unsafe-recovery.json"),
    ),
)
_HEADLINE = "restaurant/mpc-pearl-eps0.2"
_NO_CURVE = frozenset({"val_end"})
_NO_VAL = frozenset({"val8"})
_NO_SCEN = frozenset({"scen_test", "scen_ood"})

# the five-seed comparison's MPC-PEARL 0.2 seeds finished so far (seeds 0, 1, ... in order)
CAMPAIGN_MPC_PEARL = (
    "restaurant/ablation/auto-entropy-24min",
    "restaurant/ablation/auto-entropy-seed1-24min",
    "restaurant/seeds/mpc-pearl-s2",
    "restaurant/seeds/mpc-pearl-s3",
    "restaurant/seeds/mpc-pearl-s4",
)


def _r(label: str, *runs: str, absent: frozenset[str] = frozenset()) -> Entry:
    return Entry(label, tuple(f"restaurant/{r}" for r in runs), absent=absent)


RESTAURANT: tuple[Entry, ...] = (
    _r(
        "MPC-PEARL 0.2, the headline (`cpu-explore`): the paper's event-triggered infusion on "
        "PEARL's configuration + exploring starts on half the posterior-phase episodes; seed 0",
        "mpc-pearl-eps0.2",
    ),
    _r("PEARL (eps 0), the headline's preset (`cpu-explore --eps 0`); seed 0", "pearl"),
    _r(
        "MPC-SAC 0.2, the headline's preset (`cpu-explore --algo sac --eps 0.2`: no encoder); "
        "seed 0",
        "mpc-sac",
    ),
    _r(
        "PEARL (eps 0), `cpu-tuned` (the MPC-based options are inactive without MPC); seed 0",
        "ablation/pearl-tuned-60min",
    ),
    _r("PEARL (eps 0), `cpu-tuned`, seed 1", "ablation/pearl-seed1-60min"),
    _r("PEARL (eps 0), `cpu-tuned`, seed 1, 25 minutes", "ablation/pearl-seed1-25min"),
    _r(
        "MPC-PEARL 0.2, the README's main command (`default`: `cpu-explore` with 2 x 64 "
        "networks, 4 tasks per step, automatic entropy tuning; 75 iterations)",
        "main-default",
        absent=_NO_CURVE,
    ),
    _r(
        "MPC-PEARL 0.2, `cpu-explore` + automatic entropy tuning "
        "(`--set pearl.auto_entropy=true`), 24 minutes, seed 0",
        "ablation/auto-entropy-24min",
    ),
    _r(
        "MPC-PEARL 0.2, `cpu-explore` + automatic entropy tuning, 24 minutes, seed 1",
        "ablation/auto-entropy-seed1-24min",
    ),
    _r(
        "PEARL (eps 0), `cpu-explore` + automatic entropy tuning, 24 minutes, seed 0",
        "ablation/pearl-auto-entropy-24min",
    ),
    _r(
        "MPC-SAC 0.2, `cpu-explore` + automatic entropy tuning, 24 minutes, seed 0",
        "ablation/mpc-sac-auto-entropy-24min",
    ),
    _r("MPC-PEARL 0.2, `cpu-explore`, seed 2, 20 minutes", "ablation/explore-starts-seed2-20min"),
    _r(
        "MPC-PEARL 0.2, `cpu-explore` + randomised crowd timing (`train.crowd_delay_max` 20), "
        "30 minutes, seed 0",
        "ablation/crowd-delay20-30min",
    ),
    _r(
        "MPC-PEARL 0.2, the paper's event-triggered infusion only on PEARL's configuration "
        "(`cpu-tuned` with warm start, MPC buffer and cloning off; no exploring starts), seed 0",
        "ablation/event-infusion-60min",
    ),
    _r(
        "MPC-PEARL 0.2, the same (event-triggered infusion only), seed 1",
        "ablation/event-infusion-seed1-60min",
    ),
    _r(
        "MPC-PEARL 0.2, the same (event-triggered infusion only), seed 2, 20 minutes",
        "ablation/event-infusion-seed2-20min",
    ),
    _r(
        "MPC-PEARL 0.2, extended (`cpu-tuned`: `cpu` + crowds re-drawn + velocity + sensing 3 m "
        "+ BC weight 4 + clock + egocentric + people nearest first), the previous headline",
        "ablation/extended-60min",
    ),
    _r("MPC-SAC 0.2, extended (`cpu-tuned`, no encoder)", "ablation/mpc-sac-tuned-60min"),
    _r(
        "MPC-PEARL 0.2, extended (`cpu-tuned`) with the MPC handed off early: warm start "
        "annealed to zero by iteration 60 instead of 400, cloning Q-filtered",
        "ablation/handoff-60min",
    ),
    _r(
        "MPC-PEARL 0.2, extended (`cpu-tuned`) + collision penalty 50 (`env.w_collision`)",
        "ablation/collision-penalty-60min",
    ),
    _r(
        "MPC-PEARL 0.2, extended (`cpu-tuned`) + DAgger labels (`train.mpc_dagger_labels`)",
        "ablation/dagger-labels-60min",
    ),
    _r(
        "MPC-PEARL 0.2, extended without the egocentric entries and the sorting (the clock run, "
        "an earlier headline)",
        "ablation/clock-60min",
    ),
    _r(
        "MPC-PEARL 0.2, the clock run's configuration + `pearl.policy_ema` 1e-4 (averaged "
        "policy deployed)",
        "ablation/policy-ema-60min",
    ),
    _r("MPC-SAC 0.2, the clock run's configuration (no encoder)", "ablation/mpc-sac-clock-60min"),
    _r(
        "MPC-PEARL 0.2, the clock run's configuration without the clock (the no-clock run)",
        "ablation/sensing-bc4-60min",
    ),
    _r(
        "PEARL (eps 0), the no-clock run's settings (MPC extensions inactive)",
        "ablation/pearl-sensing-60min",
    ),
    _r("MPC-SAC 0.2, the no-clock run's configuration (no encoder)", "ablation/mpc-sac-30min"),
    _r(
        "MPC-PEARL 0.2, paper's algorithm (`cpu-paper`: no extension, no observation option)",
        "mpc-pearl-eps0.2-paper",
    ),
    _r(
        "MPC-PEARL 0.2, re-drawn + velocity + sensing 3 m, BC weight 1",
        "ablation/redraw-sensing-24min",
    ),
    _r(
        "MPC-PEARL 0.2, extended (`cpu` + 40 behaviours + velocity)",
        "ablation/ext-40behaviours-25min",
    ),
    _r("MPC-PEARL 0.2, paper's algorithm (`cpu-paper`), first run", "ablation/paper-12min"),
    _r("PEARL (`cpu`, eps 0)", "ablation/pearl-10min"),
    _r("MPC-SAC 0.2 (`cpu`, no encoder)", "ablation/mpc-sac-10min"),
    _r(
        "MPC-PEARL 0.2, extended (`cpu`), val = train tasks",
        "ablation/cpu-30min",
        absent=_NO_VAL,
    ),
    _r("MPC-PEARL 0.2, extended (`cpu`) + mpc.r_safe 0.4", "ablation/cpu-rsafe0.4", absent=_NO_VAL),
    Entry(
        "GP-MPC, the paper's MPC at every step (no learning), 2 QPs",
        files=_GP_MPC.files,
    ),
    _GP_MPC_TEACHER,
    Entry(
        "GP-MPC, the paper's MPC at every step (no learning), the SQP to convergence",
        files=GP_MPC_CONVERGED.files,
        absent=GP_MPC_CONVERGED.absent,
    ),
    Entry("paper MPC-PEARL 0.2 (27 h on a GPU, 7 seeds)", paper="MPC-PEARL 0.2"),
    Entry("paper PEARL", paper="PEARL"),
    Entry("paper MPC-SAC", paper="MPC-SAC"),
    Entry("paper GP-MPC", paper="GP-MPC"),
)


# ---------------------------------------------------------------- crowd perturbations


# crowd perturbations (docs/method.md §8a) on the 192 validation tasks: folder suffix, label
PERTURBATIONS = (
    ("", "none"),
    ("-delay3", "delay 3"),
    ("-delay6", "delay 6"),
    ("-delay12", "delay 12"),
    ("-speed0.7", "speed 0.7"),
    ("-speed1.3", "speed 1.3"),
)
# the perturbations settings are chosen on (never the table's): `lab.robustness
# --perturb delay=9 --perturb delay=15 --perturb speed=0.85 --perturb speed=1.15`
VALIDATION_PERTURBATIONS = (
    ("", "none"),
    ("-delay9", "delay 9"),
    ("-delay15", "delay 15"),
    ("-speed0.85", "speed 0.85"),
    ("-speed1.15", "speed 1.15"),
)
# the first rows of the robustness table; every other single-run entry of RESTAURANT with a
# 192-task validation record follows, then GP-MPC
ROBUSTNESS = (
    ("MPC-PEARL 0.2 (`cpu-explore`), 60 min", _HEADLINE),
    ("PEARL (`cpu-explore`), 60 min", "restaurant/pearl"),
    ("MPC-SAC 0.2 (`cpu-explore`), 60 min", "restaurant/mpc-sac"),
)
GP_MPC_ROW = "GP-MPC"


# the runs compared on the validation-only perturbations (the randomised crowd timing against
# the headline it modifies)
ROBUSTNESS_CHOICE = (
    ("MPC-PEARL 0.2 (`cpu-explore`), 60 min", _HEADLINE),
    (
        "MPC-PEARL 0.2, `cpu-explore` + randomised crowd timing (`train.crowd_delay_max` 20), "
        "30 min",
        "restaurant/ablation/crowd-delay20-30min",
    ),
)


# ---------------------------------------------------------------- five seeds per method


# the five-seed comparison (`python -m lab.campaign
# lab/campaigns/restaurant-seeds.json`): method -> its seed folders (seeds 0, 1, ... in
# order), each trained alone for 24 minutes with `--preset cpu-auto`; a folder is listed once its
# campaign run and evaluations have finished. These methods are trained by the learning harness,
# so they also have the learning-curve table.
CURVE_SEED_GROUPS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("MPC-PEARL 0.2", CAMPAIGN_MPC_PEARL),
    (
        "PEARL",
        (
            "restaurant/ablation/pearl-auto-entropy-24min",
            "restaurant/seeds/pearl-s1",
            "restaurant/seeds/pearl-s2",
            "restaurant/seeds/pearl-s3",
            "restaurant/seeds/pearl-s4",
        ),
    ),
    (
        "MPC-SAC 0.2",
        (
            "restaurant/ablation/mpc-sac-auto-entropy-24min",
            "restaurant/seeds/mpc-sac-s1",
            "restaurant/seeds/mpc-sac-s2",
            "restaurant/seeds/mpc-sac-s3",
            "restaurant/seeds/mpc-sac-s4",
        ),
    ),
)
# `lab/campaigns/grbal-seeds.json`: `--preset cpu`, 24 minutes alone per seed; GrBAL's
# trainer writes no curve.json, so it is in the seed tables only
GRBAL_SEEDS = ("GrBAL", tuple(f"restaurant/seeds/grbal-s{s}" for s in range(5)))
# the five-seed campaign above with GrBAL: the `recipe` configuration on an earlier version of
# the code, trained on a faster 2-core machine
CAMPAIGN_SEED_GROUPS = (*CURVE_SEED_GROUPS, GRBAL_SEEDS)
# the recipe's five MPC-PEARL 0.2 seeds on the current version (`lab/screens/student-recipe.json`,
# arm `recipe`: `--preset recipe --minutes 24 --seed S`)
RECIPE_MPC_PEARL = tuple(f"restaurant/student-recipe-screen/recipe-s{s}" for s in range(5))
# the paper's three learned methods at the recipe on the current version, every seed trained
# alone for 24 minutes on one kind of 2-core machine (`lab/screens/methods-recipe.json`: PEARL
# with `--eps 0`, MPC-SAC with `--algo sac`), and GrBAL: the README's summary, the paper's table
# side by side and the five-seed table
SEED_GROUPS = (
    ("MPC-PEARL 0.2", RECIPE_MPC_PEARL),
    ("PEARL", tuple(f"restaurant/methods-recipe-screen/pearl-s{s}" for s in range(5))),
    ("MPC-SAC 0.2", tuple(f"restaurant/methods-recipe-screen/mpc-sac-s{s}" for s in range(5))),
    GRBAL_SEEDS,
)
# evaluation sets of the seed tables: kind, label
SEED_SETS = (
    ("test", "24 test tasks"),
    ("val8", "192 validation tasks"),
    ("online", "24 test tasks, online"),
    ("ood", "24 OOD tasks"),
    ("scen_test", "paper's 25 test scenarios"),
    ("scen_ood", "paper's 25 OOD scenarios"),
)
# the paper's ordering claim, as pairs (A, B): A > B in the paper's table
PAPER_ORDER = (
    ("MPC-PEARL 0.2", "PEARL"),
    ("PEARL", "MPC-SAC 0.2"),
    ("MPC-PEARL 0.2", "MPC-SAC 0.2"),
    # section IV-A: "GrBAL presents the worst performance", "MPC-SAC shows slightly better results
    # compared to GrBAL"
    ("MPC-SAC 0.2", "GrBAL"),
    ("MPC-PEARL 0.2", "GrBAL"),
)


# ---------------------------------------------------------------- the seeds' learning curves


# the learning harness's evaluation points of the five-seed runs (every 6 minutes)
CURVE_MINUTES = (6, 12, 18, 24)
# values of a curve point shown per method: key in curve.json's points, label
CURVE_VALUES = (
    ("val_SR", "SR, 24 validation tasks"),
    ("val_CFR", "CFR, 24 validation tasks"),
    ("test_SR", "SR, 24 test tasks"),
)


# ---------------------------------------------------------------- the main command's seeds


# recipes tried for the README's main command (`python -m experiments.restaurant`, the `default`
# preset, 75 iterations), each on the seeds listed: label, ((seed, folder under
# results/restaurant), ...).
# Commands: lab/campaigns/main-*.json (`python -m lab.campaign FILE`).
# the recipes run on all ten seeds 0-9: (seed, folder under results/restaurant)
MAIN_DEFAULT = ((0, "main-default"), *((s, f"main-seeds/default-s{s}") for s in range(1, 10)))
MAIN_RS1 = tuple((s, f"main-seeds/rs1-alpha02-s{s}") for s in range(10))
MAIN_IT95 = tuple((s, f"main-seeds/default-it95-s{s}") for s in range(10))
MAIN_RS1_IT95 = tuple((s, f"main-seeds/rs1-alpha02-it95-s{s}") for s in range(10))
MAIN_SEEDS: tuple[tuple[str, tuple[tuple[int, str], ...]], ...] = (
    ("`default`", MAIN_DEFAULT),
    (
        "+ MPC warm start for 20 iterations (`train.mpc_demo_share=1.0`, "
        "`train.mpc_demo_iterations=20`)",
        ((0, "main-seeds/warmstart20-s0"),),
    ),
    (
        "+ three posterior-phase episodes per task (`train.posterior_episodes=3`)",
        ((1, "main-seeds/posterior3-s1"), (2, "main-seeds/posterior3-s2")),
    ),
    (
        "+ three posterior-phase episodes + entropy target 0 (`pearl.target_entropy=0.0`)",
        ((1, "main-seeds/post3-tent0-s1"), (2, "main-seeds/post3-tent0-s2")),
    ),
    ("+ entropy target 0", ((2, "main-seeds/tent0-s2"),)),
    (
        "+ Adam step 1e-3 on log alpha (`pearl.alpha_lr`, since removed)",
        ((2, "main-seeds/alpha-lr1e-3-s2"),),
    ),
    (
        "+ 8 tasks per gradient step, 70 iterations (`pearl.meta_batch=8`, `train.iterations=70`)",
        ((1, "main-seeds/mb8-it70-s1"),),
    ),
    (
        "+ fixed temperature, alpha 1 (`pearl.auto_entropy=false`: temperature 1 / reward scale 5)",
        ((1, "main-seeds/fixed1-s1"), (2, "main-seeds/fixed1-s2")),
    ),
    (
        "+ fixed temperature, reward scale 10 (`pearl.auto_entropy=false`, "
        "`pearl.reward_scale=10`: as alpha 0.5)",
        ((1, "main-seeds/fixed-rs10-s1"), (2, "main-seeds/fixed-rs10-s2")),
    ),
    (
        "+ target V updated 4x faster (`pearl.tau=0.02`; paper 0.005)",
        ((1, "main-seeds/tau02-s1"), (2, "main-seeds/tau02-s2")),
    ),
    (
        "+ reward scale 1 and alpha starting at 0.2 (`pearl.reward_scale=1`, "
        "`pearl.init_alpha=0.2`: for the same Q the actor's and alpha's steps are those of scale 5 "
        "and alpha 1, while the Q and V targets are 5x smaller; its alpha is on the scale-1 "
        "footing, x5 to compare)",
        MAIN_RS1,
    ),
    (
        "`default`, 95 iterations (`--iterations 95`; seeds 2-9 resumed from their 75-iteration "
        "checkpoints)",
        MAIN_IT95,
    ),
    (
        "reward scale 1, alpha starting at 0.2, 95 iterations (resumed from the 75-iteration "
        "checkpoints)",
        MAIN_RS1_IT95,
    ),
)


# the recipes of the main command run on all ten seeds 0-9, compared with seeds as the unit
MAIN_SEED_SUMMARY: tuple[tuple[str, tuple[str, ...]], ...] = tuple(
    (name, tuple(f"restaurant/{run}" for _, run in runs))
    for name, runs in (
        ("`default`", MAIN_DEFAULT),
        ("reward scale 1, init alpha 0.2", MAIN_RS1),
        ("`default`, 95 iterations", MAIN_IT95),
        ("reward scale 1, init alpha 0.2, 95 iterations", MAIN_RS1_IT95),
    )
)
MAIN_SEED_SETS = (("val8", "192 validation tasks"), ("test", "24 test tasks"))
MAIN_PASS = 0.3  # the main command's threshold on test and validation SR


# ---------------------------------------------------------------- the sidewalk's seeds


# the sidewalk's seeds (`python -m lab.campaign lab/campaigns/sidewalk-seeds.json`,
# `--preset cpu-auto` with the data windows kept, 30 minutes alone per seed): method -> its seed
# folders (seeds 0, 1, ... in order), listed once the run has finished
SIDEWALK_SEED_GROUPS: tuple[tuple[str, tuple[str, ...]], ...] = (
    (
        "MPC-PEARL 0.2",
        (
            "sidewalk/seeds/mpc-pearl-s0",
            "sidewalk/seeds/mpc-pearl-s1",
            "sidewalk/seeds/mpc-pearl-s2",
        ),
    ),
    ("PEARL", ("sidewalk/seeds/pearl-s0", "sidewalk/seeds/pearl-s1", "sidewalk/seeds/pearl-s2")),
)
# the sidewalk's evaluation sets (Zara 01): online adaptation is the paper's sidewalk protocol
SIDEWALK_SEED_SETS = (
    ("online", "6 test windows, online"),
    ("test", "6 test windows, after two adaptation episodes"),
    ("ood", "5 windows with annotation holes"),
)
SIDEWALK_ORDER = (("MPC-PEARL 0.2", "PEARL"),)
