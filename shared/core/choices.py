"""The named choices the project offers, defined once: the CLI's ``choices=``, the config checks,
the API's request models and the docs all read them from here."""

from __future__ import annotations

from typing import Final

DETECTIONS: Final = (
    "node",
    "neighbourhood",
    "custom",
)  # D(p): {p}, N[p], a graph file's table (docs/SPEC.md section 1)
VARIANTS: Final = ("cepg", "cepg+", "c-cepg")  # own belief, sensing range, collective belief (docs/SPEC.md section 3)
CE_STATES: Final = ("shared", "all")  # where the cross entropy of Eq. 9 counts (docs/SPEC.md section 10)
BELIEFS: Final = ("em", "true")  # the robots' belief model while training: EM-estimated or the true one
ESTIMATORS: Final = ("em", "eq8")  # how `mures estimate` fits Gamma_hat
TEAM_SEARCHERS: Final = ("fhpe-sa", "c-cepg")  # what robots fly together when their links allow (core/team.py)
ALGORITHMS: Final = ("cepg", "maddpg", "masac", "facmac", "mambpo", "mappo")  # `mures train --algorithm`
BUILTIN_MAPS: Final = ("office", "museum", "ward")  # ward: ours, not the paper's (docs/SPEC.md section 7)
