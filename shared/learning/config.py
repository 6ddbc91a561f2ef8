"""The trainer's configuration, the one source of truth for its defaults (no torch here).

Every field of ``TrainConfig`` is a `mures train` flag (``add_flags`` builds them from the fields:
name, default, type, choices and help), the retraining API's parameters take their defaults from
it (training_server/api/models.py), and a snapshot stores it whole (policy.json "training").
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from dataclasses import MISSING, asdict, dataclass, field, fields
from typing import Any

from shared.core.choices import ALGORITHMS, BELIEFS, CE_STATES, VARIANTS

# torch threads of a training process (`mures train --threads`, the server's training runs): a
# team's tensors are small. 30,208 episodes of CE-PG on OFFICE, N = 3 (B = 256): 23.5 s on one
# thread, 23.0 s on two, a quiet 2-core x86 VM; beside one other busy process 45 s on one and
# 139 s on two (each small operation waits at its end for the thread that lost the core)
TORCH_THREADS = 1
# a resumable MARL run's checkpoint interval, seconds of training (`mures train --checkpoint-every`,
# the experiments' teams): a MUSEUM N = 4 team's checkpoint with a full replay buffer is 1.5 GB,
# 8-17 s to write beside two jobs, under 3 % of the interval (benchmarks/bench_checkpoint.py)
CHECKPOINT_EVERY_S = 600.0


def _opt(help: str, **kw: Any) -> Any:
    """Field metadata: the flag's help, and optionally ``choices``, ``parse`` (text -> value),
    ``metavar``, ``flag`` (False: not a `mures train` flag, set elsewhere)."""
    return {"help": help, **kw}


def _int_at_least(text: str, low: int, what: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if v < low:
        raise argparse.ArgumentTypeError(f"expected {what}, got {v}")
    return v


def positive_int(text: str) -> int:
    """An integer >= 1 (argparse type)."""
    return _int_at_least(text, 1, "a positive integer")


def whole_number(text: str) -> int:
    """An integer >= 0 (argparse type)."""
    return _int_at_least(text, 0, "a whole number >= 0")


def _float_where(text: str, ok: Callable[[float], bool], what: str) -> float:
    """A finite number for which ``ok`` holds (argparse type), else an error naming ``what``."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if math.isinf(v) or math.isnan(v) or not ok(v):
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
    return v


def seconds(text: str) -> float:
    """A number of seconds >= 0 (argparse type)."""
    return _float_where(text, lambda v: v >= 0, "a number of seconds >= 0")


def positive_float(text: str) -> float:
    """A finite number above 0 (argparse type)."""
    return _float_where(text, lambda v: v > 0, "a number above 0")


def non_negative(text: str) -> float:
    """A finite number >= 0 (argparse type)."""
    return _float_where(text, lambda v: v >= 0, "a number >= 0")


def floats(text: str) -> list[float]:
    """One number or comma-separated numbers (one per robot)."""
    try:
        vals = [float(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number or comma-separated numbers, got {text!r}") from None
    if not vals or any(math.isnan(v) for v in vals):
        raise argparse.ArgumentTypeError(f"expected a number or comma-separated numbers, got {text!r}")
    return vals


@dataclass
class TrainConfig:
    """Everything that defines a training run (stored in the snapshot's metadata)."""

    robots: int = field(metadata=_opt("number of robots N", flag=False))
    algorithm: str = field(
        default="cepg",
        metadata=_opt(
            "training method: CE-PG (with its variants) or a MARL baseline, whose own hyperparameters "
            "take --hp KEY=VALUE (docs/SPEC.md section 11)",
            choices=ALGORITHMS,
        ),
    )
    episodes: int = field(default=400_000, metadata=_opt("training episodes", parse=positive_int))
    beta: list[float] = field(
        default_factory=lambda: [0.5],
        metadata=_opt("Eq. 9's beta, one value or one per robot (1 = PG)", parse=floats),
    )
    lr: list[float] = field(
        default_factory=lambda: [1e-2],
        metadata=_opt("Adam learning rate alpha_i, one value or one per robot", parse=floats),
    )
    lr_final: float = field(
        default=0.1, metadata=_opt("the learning rate decays linearly to this fraction of itself over the run")
    )
    variant: str = field(
        default="cepg", metadata=_opt("own belief, sensing range, or collective belief", choices=VARIANTS)
    )
    batch: int = field(
        default=256,
        metadata=_opt(
            "episodes per update (B), over all processes; for a MARL baseline, episodes simulated side by side",
            parse=positive_int,
        ),
    )
    eps: float = field(default=0.1, metadata=_opt("smoothing of the cross entropy, pi~ = (1-eps) pi + eps U"))
    ce_fraction: float = field(default=0.25, metadata=_opt("share of decisions the cross entropy is estimated on"))
    j_unit: float = field(
        default=1.0,
        metadata=_opt(
            "J's unit in steps (1: Eq. 9's natural units; 0: the run's running mean capture time, the general "
            "policy's own scale)",
            parse=non_negative,
        ),
    )
    ce_states: str = field(
        default="shared",
        metadata=_opt(
            "where the cross entropy counts: states two robots share (node, belief), or all", choices=CE_STATES
        ),
    )
    belief: str = field(
        default="em",
        metadata=_opt("robots' belief model: Gamma_hat_0 re-estimated by EM, or the true model", choices=BELIEFS),
    )
    em_first: int = field(default=8192, metadata=_opt("episodes before the first EM update", parse=positive_int))
    em_every: int = field(default=100_000, metadata=_opt("episodes between later EM updates", parse=positive_int))
    em_missions: int = field(default=512, metadata=_opt("missions recorded for each EM update", parse=positive_int))
    em_max_iter: int = field(default=300, metadata=_opt("EM forward-backward passes at most", parse=positive_int))
    em_pseudo_count: float = field(
        default=0.0,
        metadata=_opt(
            "EM's Dirichlet prior: expected transitions added to each entry of Gamma_hat's support (0: maximum "
            "likelihood, Algorithm 2 as the paper writes it; a server's retraining: 1 below 100 nodes, up to 20 above)",
            parse=non_negative,
        ),
    )
    em_b0_pseudo_count: float = field(
        default=0.0,
        metadata=_opt(
            "EM's Dirichlet prior: expected starts added to every node of b0 (the server's: as --em-pseudo-count's)",
            parse=non_negative,
        ),
    )
    speed: float | None = field(
        default=None,
        metadata=_opt(
            "robots' speed in m/s: each move takes its edge's travel time (the graph's edge_lengths_m) in "
            "ticks of --tick seconds and the target moves once a tick (docs/continuous-world.md); unset: every "
            "move is one step, the paper's model",
            parse=positive_float,
            metavar="M_PER_S",
        ),
    )
    tick: float = field(
        default=1.0,
        metadata=_opt("the mission clock's tick in seconds, with --speed", parse=positive_float, metavar="S"),
    )
    node_bias: float = field(
        default=10.0,
        metadata=_opt(
            "a fine-tune of the general policy also learns each robot's preference for each node of the map, "
            "at this many times the learning rate (docs/general-policy.md); 0: the network alone",
            parse=non_negative,
            metavar="RATE",
        ),
    )
    seed: int = field(default=0, metadata=_opt("random seed", flag=False))
    device: str = field(default="cpu", metadata=_opt("torch device", flag=False))
    hidden: int | None = field(
        default=None, metadata=_opt("hidden units (default 2n, the paper's)", parse=positive_int, metavar="H")
    )

    def per_robot(self, values: list[float], name: str) -> list[float]:
        if len(values) == 1:
            return values * self.robots
        if len(values) != self.robots:
            raise ValueError(f"{name}: give one value or one per robot ({self.robots}), got {len(values)}")
        return list(values)

    def check(self) -> None:
        if self.algorithm not in ALGORITHMS:
            raise ValueError(f"unknown algorithm {self.algorithm!r} (expected one of {', '.join(ALGORITHMS)})")
        if self.algorithm != "cepg" and self.variant != "cepg":
            raise ValueError(
                f"variant {self.variant} is CE-PG's; {self.algorithm} trains robots with their own beliefs"
            )
        if self.variant not in VARIANTS:
            raise ValueError(f"unknown variant {self.variant!r} (expected one of {', '.join(VARIANTS)})")
        if self.ce_states not in CE_STATES:
            raise ValueError(f"ce_states must be one of {', '.join(CE_STATES)}, got {self.ce_states!r}")
        if self.belief not in BELIEFS:
            raise ValueError(f"belief must be one of {', '.join(BELIEFS)}, got {self.belief!r}")
        for b in self.per_robot(self.beta, "beta"):
            if not 0.0 <= b <= 1.0:
                raise ValueError(f"beta must be in [0, 1], got {b}")
        for a in self.per_robot(self.lr, "lr"):
            if not 0.0 < a < 1.0:
                raise ValueError(f"learning rate must be in (0, 1), got {a}")
        if not 0.0 < self.ce_fraction <= 1.0:
            raise ValueError(f"ce_fraction must be in (0, 1], got {self.ce_fraction}")
        if not 0.0 < self.lr_final <= 1.0:
            raise ValueError(f"lr_final must be in (0, 1], got {self.lr_final}")
        if not (self.j_unit >= 0 and math.isfinite(self.j_unit)):
            raise ValueError(f"j_unit must be a number >= 0 (0: the running mean capture time), got {self.j_unit}")
        if not 0.0 < self.eps <= 1.0:
            raise ValueError(f"eps must be in (0, 1], got {self.eps}")
        if self.batch < 1 or self.episodes < 1:
            raise ValueError("batch and episodes must be positive")
        if self.speed is not None and not (self.speed > 0 and math.isfinite(self.speed)):
            raise ValueError(f"speed must be a number of m/s above 0, got {self.speed}")
        if not (self.em_pseudo_count >= 0 and self.em_b0_pseudo_count >= 0):
            raise ValueError("EM's pseudo-counts must be numbers >= 0")
        if not (self.node_bias >= 0 and math.isfinite(self.node_bias)):
            raise ValueError(f"node_bias must be a number >= 0 (0: the network alone), got {self.node_bias}")
        if not (self.tick > 0 and math.isfinite(self.tick)):
            raise ValueError(f"tick must be a number of seconds above 0, got {self.tick}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def default(name: str) -> Any:
    """A field's default value (the one source of the trainer's defaults)."""
    f = next(f for f in fields(TrainConfig) if f.name == name)
    if f.default is not MISSING:
        return f.default
    factory: Callable[[], Any] = f.default_factory  # type: ignore[assignment]
    return factory()


# A fine-tune of the general policy on one map (`mures train --init general`, a training server's
# retraining of a general version) takes these where it is not told otherwise: J in the general
# training's own unit (j_unit 0: the running mean capture time), its beta, a tenth of the trainer's
# learning rate, and EM with a Dirichlet prior (``fine_tune_defaults``); its beliefs start on the
# uniform walk it was trained with (docs/general-policy.md, measured by benchmarks/general_finetune.py).
FINE_TUNE: dict[str, Any] = {
    "lr": [1e-3],
    "beta": [0.9],
    "j_unit": 0.0,
}
FINE_TUNE_BATCH_ELEMENTS = 24_000  # a fine-tune's batch: this over n episodes, within [16, 256], as in its training
FINE_TUNE_EM_ELEMENTS = 128_000  # its EM's missions: this over n, within [64, 512]
EM_PRIOR_FROM_NODES = 100  # below: EM's pseudo-count 1 (the paper's maps)
EM_PRIOR_NODES_PER_COUNT = 15  # from EM_PRIOR_FROM_NODES: one pseudo-count per this many nodes ...
EM_PRIOR_MAX = 20.0  # ... at most this


def em_prior(n: int) -> float:
    """EM's Dirichlet pseudo-count (on each entry of Gamma_hat's support, and on each node of b0)
    for a map of n nodes, where a fine-tune of the general policy and a training server's
    retraining are not told one: 1 below 100 nodes (the paper's maps, where the fine-tune was
    measured with it), then n / 15 rounded down, at most 20 (6 at 100 nodes, 20 from 300). On
    larger floors beliefs on EM's model from a few hundred missions captured later than on the
    uniform walk unless the prior was strong, whichever walk the target took: 20 left no
    separable cost at 300 and 1,000 nodes (docs/general-policy.md, "EM's prior on a large floor";
    benchmarks/general_em_prior.py)."""
    if n < EM_PRIOR_FROM_NODES:
        return 1.0
    return float(min(EM_PRIOR_MAX, n // EM_PRIOR_NODES_PER_COUNT))


def fine_tune_defaults(n: int) -> dict[str, Any]:
    """FINE_TUNE for a map of n nodes, with its batch and EM's missions: both scale as 1 / n, so
    that what a rollout holds (every state's belief, n floats) and what EM holds (every mission-step's
    likelihood, filter and smoother, n floats each) stay near a 100-node map's (a 1,000-node
    fine-tune peaked at 1.3-2.0 GB, docs/general-policy.md). The paper's maps keep 256 and 512. EM's
    pseudo-counts are ``em_prior(n)``."""
    prior = em_prior(n)
    return {
        **FINE_TUNE,
        "em_pseudo_count": prior,
        "em_b0_pseudo_count": prior,
        "batch": int(min(max(FINE_TUNE_BATCH_ELEMENTS // n, 16), 256)),
        "em_missions": int(min(max(FINE_TUNE_EM_ELEMENTS // n, 64), 512)),
    }


# Flags whose value a MARL baseline or a fine-tune of the general policy (FINE_TUNE) takes from its
# own defaults when they are not given: whose defaults they are.
METHOD_DEFAULTS = {
    "episodes": "a MARL baseline's",
    "batch": "a MARL baseline's or a general policy fine-tune's",
    "lr": "a MARL baseline's or a general policy fine-tune's",
    "beta": "a general policy fine-tune's",
    "j_unit": "a general policy fine-tune's",
    "em_missions": "a general policy fine-tune's",
    "em_pseudo_count": "a general policy fine-tune's",
    "em_b0_pseudo_count": "a general policy fine-tune's",
}


def add_flags(parser: argparse.ArgumentParser) -> None:
    """One flag per TrainConfig field (``--em-first`` for ``em_first``), defaults from the fields.
    The flags of METHOD_DEFAULTS default to None (``from_flags`` fills in CE-PG's default), so
    that a MARL baseline or a general policy's fine-tune can tell an unset flag from a given one."""
    for f in fields(TrainConfig):
        meta = f.metadata
        if not meta.get("flag", True):
            continue
        dflt = default(f.name)
        parse = meta.get("parse") or (float if f.type in ("float", float) else str)
        shown = ",".join(f"{x:g}" for x in dflt) if isinstance(dflt, list) else dflt
        kw: dict[str, Any] = {"default": dflt, "help": f"{meta['help']} (default {shown})", "dest": f.name}
        if f.name in METHOD_DEFAULTS:
            kw.update(default=None, help=f"{meta['help']} (default {shown}; {METHOD_DEFAULTS[f.name]} own otherwise)")
        if "choices" in meta:
            kw["choices"] = meta["choices"]
        else:
            kw["type"] = parse
        if "metavar" in meta:
            kw["metavar"] = meta["metavar"]
        parser.add_argument("--" + f.name.replace("_", "-"), **kw)


def from_flags(args: argparse.Namespace, **given: Any) -> TrainConfig:
    """A TrainConfig from the parsed flags of ``add_flags``; ``given`` sets the other fields."""
    values = {f.name: getattr(args, f.name) for f in fields(TrainConfig) if f.metadata.get("flag", True)}
    for name in METHOD_DEFAULTS:
        if values[name] is None:
            values[name] = default(name)
    return TrainConfig(**values, **given)
