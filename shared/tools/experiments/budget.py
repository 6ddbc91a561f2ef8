"""How large a run of the experiments is (``Budget``: the paper's protocol ``FULL`` or ``QUICK``),
what it covers (the experiments, maps, methods) and ``budget``, which checks a run's options."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, replace

EXPERIMENTS = ("fig4", "fig5", "fig6", "fig7", "fig8", "fig9", "fig10", "fig11", "fig12", "fig13", "marl")


PLANNERS = ("fhpe", "fhpe-sa", "milp", "d-milp")
PAPER_MAPS = ("office", "museum")
MARL = ("maddpg", "masac", "facmac", "mambpo", "mappo")  # shared.learning.marl.MARL_ALGORITHMS


@dataclass(frozen=True)
class Budget:
    """How large each run is: the paper's protocol, or ``--quick`` (every experiment together
    inside CI, minutes on 2 cores: the learned teams are then barely trained, so quick numbers
    show that the pipeline works, not how good the method is)."""

    quick: bool
    episodes: int  # evaluation episodes per cell (the paper: 1500)
    train: int  # training episodes per learned team (the paper: 4 x 10^5)
    planner: int  # episodes for fhpe and milp (one MILP solve per team step); fhpe-sa runs 4x
    milp_limit: float  # HiGHS time limit per solve, seconds
    teams: tuple[int, ...]  # team sizes N of the sweeps (fig6, fig9, fig10)
    marl_train: int | None = None  # training episodes per MARL baseline; None: each method's default budget
    seeds: tuple[int, ...] = (0,)  # training seeds of fig5's teams (the other figures: seed 0)
    d_milp: int | None = None  # episodes for d-milp (N solves per team step); None: ``planner``
    maps: tuple[str, ...] = PAPER_MAPS  # the maps every figure runs on (`--maps`)
    robots: tuple[int, ...] | None = None  # team sizes of fig6, fig7, fig9, fig10 (`--robots`); None: theirs
    marl_train_for: tuple[tuple[str, int], ...] = ()  # (method, episodes): budgets that replace marl_train
    add: bool = False  # `--add`: fig5 to fig13 keep the recorded rows of the maps and team sizes not run
    overwrite: bool = False  # `--overwrite`: a run may drop or replace recorded rows (``refuse_loss``)
    marl_methods: tuple[str, ...] = MARL  # the MARL baselines the figures fly

    def with_train(self, episodes: int | None) -> Budget:
        if episodes is None:
            return self
        return replace(self, train=episodes, marl_train=episodes, marl_train_for=())

    def scaled(self, fraction: float) -> Budget:
        """Every learned team's budget times ``fraction`` (`--train-fraction`), the methods' ratios
        kept: a run at team sizes whose full budget does not fit states its own in every row."""
        if not 0 < fraction <= 1:
            raise ValueError(f"--train-fraction takes a fraction in (0, 1], not {fraction:g}")

        def part(episodes: int) -> int:
            return max(1, round(episodes * fraction))

        return replace(
            self,
            train=part(self.train),
            marl_train=None,
            marl_train_for=tuple((m, part(self.marl_episodes(m))) for m in self.marl_methods),
        )

    def marl_episodes(self, method: str) -> int:
        """Training episodes of a MARL baseline's teams in the figures: ``marl_train_for``'s, else
        ``marl_train``, else the method's default budget (its plateau on OFFICE, N = 4)."""
        return dict(self.marl_train_for).get(method) or self.marl_train or default_marl_episodes(method)

    def planner_episodes(self, method: str) -> int:
        """Episodes a planner's cell flies: ``planner``, 4x for fhpe-sa, ``d_milp`` for d-milp."""
        return {"fhpe-sa": 4 * self.planner, "d-milp": self.d_milp or self.planner}.get(method, self.planner)

    def sizes(self, default: Iterable[int]) -> tuple[int, ...]:
        """The team sizes of a sweep whose own are ``default``, as ``--robots`` narrows them."""
        return tuple(default) if self.robots is None else self.robots


# The MARL baselines train for their default budgets (marl_train None): each method's plateau on
# OFFICE, N = 4, set with its evidence in shared/learning/marl/<method>.py
FULL = Budget(False, 1500, 400_000, 100, 1.0, (1, 2, 3, 4, 5), seeds=(0, 1, 2), d_milp=30)
QUICK = Budget(True, 200, 2_000, 1, 0.05, (2, 4), marl_train=1_000)
# a setup's "marl_training_episodes" when no one budget is given: the defaults, or (--train-fraction)
# a fraction of each; "marl_training_episodes_by_method" has the numbers
MARL_DEFAULT, MARL_OWN = "each method's default", "each method's own"
SEED = 1  # evaluation seed of every cell (training seeds: 0)
ETAS = (0.0, 0.1, 0.3, 0.5)  # the paper's sensor-noise grid (Fig. 9-11)
LEARNED = {"pg": ("cepg", 1.0), "cepg": ("cepg", 0.5), "cepg+": ("cepg+", 0.5), "c-cepg": ("c-cepg", 0.5)}
BETAS = (0.1, 0.3, 0.5, 0.7, 0.9, 1.0)  # fig5's beta of Eq. 9 (1: PG)


def default_marl_episodes(method: str) -> int:
    """A MARL baseline's default training budget (its plateau on OFFICE, N = 4)."""
    from shared.learning.marl import hyperparameters

    return int(hyperparameters(method).episodes)


def budget(
    name: str,
    quick: bool,
    train_episodes: int | None = None,
    maps: tuple[str, ...] | None = None,
    robots: tuple[int, ...] | None = None,
    train_fraction: float | None = None,
    add: bool = False,
    overwrite: bool = False,
) -> Budget:
    """The Budget of a run of experiment ``name`` (``run``'s arguments), checked: a ValueError names
    what is wrong."""
    if train_episodes is not None and train_fraction is not None:
        raise ValueError("give --train-episodes or --train-fraction, not both")
    b = (QUICK if quick else FULL).with_train(train_episodes)
    if train_fraction is not None:
        b = b.scaled(train_fraction)
    if name != "all" and name not in EXPERIMENTS:
        raise ValueError(f"experiment {name!r} is not implemented (have: {', '.join(EXPERIMENTS)}, all)")
    if add:
        if name in ("fig4", "marl"):
            raise ValueError(
                f"--add keeps rows of other maps and team sizes; {name} is not recorded by them: run it without --add"
            )
        b = replace(b, add=True)
    if overwrite:
        if name in ("fig4", "marl"):
            raise ValueError(f"--overwrite lets a run drop recorded rows of maps and team sizes; {name} has none")
        b = replace(b, overwrite=True)
    if maps is not None:
        if not maps or any(m not in PAPER_MAPS for m in maps):
            raise ValueError(f"--maps takes {' and/or '.join(PAPER_MAPS)} (comma-separated), not {','.join(maps)!r}")
        b = replace(b, maps=tuple(dict.fromkeys(maps)))
    if robots is not None:
        if not robots or any(n < 1 or n > 5 for n in robots):
            raise ValueError(f"--robots takes team sizes 1 to 5 (comma-separated), not {','.join(map(str, robots))}")
        b = replace(b, robots=tuple(sorted(set(robots))))
    return b
