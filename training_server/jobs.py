"""Training runs: EM on the fleet's own records, CE-PG in simulation under the estimated model,
an evaluation gate, and a new immutable policy version.

A run executes in a separate process (multiprocessing "spawn": no Zenoh session or lock is
inherited), one at a time, that dies with the server (``_die_with_parent``). The process reads the
episodes through its own database connection, reports progress on a queue, polls a cancel event,
and writes its snapshot under ``<data>/staging/<run>`` (removed at the server's next start if it
is killed); the supervisor thread in the server turns a passed snapshot into the next version. A
failed, cancelled or gated-out run leaves the current policy untouched.
"""

from __future__ import annotations

import ctypes
import json
import logging
import math
import multiprocessing as mp
import os
import queue
import shutil
import signal
import threading
import time
import traceback
from dataclasses import replace
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, model_validator

from shared.learning import config as train_config
from training_server.methods import (
    DEFAULT_CANDIDATES,
    METHODS,
    MarlMethod,
    Method,
    RunFolder,
    TrainedTeam,
    check_hyperparameters,
    default_episodes,
    train_team,
)

MAX_TEAM_SIZES = 16  # team sizes one run may train a team for (and the largest such size)

log = logging.getLogger("mures.server.training")


def _integral(v: Any) -> Any:
    """JSON Schema counts 5.0 as an integer: such a float is taken as that integer (5.5, "5" and
    true are still refused by the strict models)."""
    return int(v) if isinstance(v, float) and v.is_integer() else v


# in an integer field of a request body, after its bounds: Annotated[int, Field(ge=.., le=..), INTEGRAL]
# (bounds before the validator, so that the OpenAPI document shows them as minimum and maximum)
INTEGRAL = BeforeValidator(_integral)


class TrainingParams(BaseModel):
    """A retrain's parameters: the body of POST /api/v1/training-runs (every field optional) and what
    the training process runs. The trainer's own settings default to TrainConfig's (one source)."""

    model_config = ConfigDict(extra="forbid", strict=True)

    algorithm: Method | Literal["best"] = Field(
        "cepg",
        description="the method that trains the new version's teams (training_server/methods.py): cepg (with "
        "variant, beta and lr), pg (CE-PG with beta = 1), maddpg, masac, facmac, mambpo or mappo (their "
        "hyperparameters, docs/SPEC.md section 11), or best: every one of `candidates` trained, evaluated beside "
        "the current version on the gate's episodes, and the one that captures soonest published",
    )
    candidates: list[Method] | None = Field(
        None,
        min_length=1,
        max_length=len(METHODS),
        json_schema_extra={"uniqueItems": True},
        description=f"the methods algorithm best trains (default {', '.join(DEFAULT_CANDIDATES)}: those best "
        "somewhere in the recorded protocol); not used by a run of one method",
    )
    episodes: Annotated[int, Field(ge=256, le=10_000_000), INTEGRAL] | None = Field(
        None,
        description="training episodes of every team of the run (default: each method's own budget, the "
        "protocol's: CE-PG and PG 400,000, a MARL baseline its plateau, times budget_fraction; CE-PG runs in "
        f"whole batches of {train_config.default('batch')}: a number in between is rounded up, and the run says so)",
    )
    budget_fraction: float = Field(
        1.0,
        gt=0.0,
        le=1.0,
        allow_inf_nan=False,
        description="the compute budget: each team trains for this fraction of its method's default episodes "
        "(without episodes); the run's record states every team's episodes and wall time",
    )
    team_sizes: list[Annotated[int, Field(ge=1, le=MAX_TEAM_SIZES), INTEGRAL]] | None = Field(
        None,
        max_length=MAX_TEAM_SIZES,
        description="team sizes k to train a team for besides the fleet's N (one training each, one after "
        "another): a mission of k robots flies the team built for k, and robots switch to the team for those "
        "left when a teammate drops out (default: N alone)",
    )
    variant: Literal["cepg", "cepg+", "c-cepg"] | None = Field(  # shared.core.choices.VARIANTS
        None, description="CE-PG's variant (default: the current version's where it is a CE-PG team, else cepg)"
    )
    hyperparameters: dict[MarlMethod, dict[str, int | float | bool]] = Field(
        default_factory=dict,
        description='a MARL baseline\'s hyperparameters by method, e.g. {"masac": {"lr": 0.0001}}, used when the run '
        "trains that method (checked when the run starts: an unknown name fails it at once, naming it)",
    )
    beta: float | None = Field(
        None,
        ge=0.0,
        le=1.0,
        allow_inf_nan=False,
        description=f"Eq. 9's beta for cepg (default {train_config.default('beta')[0]:g}; "
        f"{train_config.FINE_TUNE['beta'][0]:g} for a fine-tune of the general policy; pg is CE-PG with beta = 1, "
        "whatever this says)",
    )
    lr: float | None = Field(
        None,
        gt=0.0,
        lt=1.0,
        allow_inf_nan=False,
        description=f"CE-PG's Adam learning rate (default {train_config.default('lr')[0]:g}; "
        f"{train_config.FINE_TUNE['lr'][0]:g} for a fine-tune of the general policy)",
    )
    seed: Annotated[int, Field(ge=0, le=2**53 - 1), INTEGRAL] = Field(
        train_config.default("seed"), description="training and gate seed"
    )
    max_records: Annotated[int, Field(ge=1, le=10_000_000), INTEGRAL] = Field(
        20_000, description="newest episode records used by EM"
    )
    em_max_iter: Annotated[int, Field(ge=1, le=100_000), INTEGRAL] = Field(
        train_config.default("em_max_iter"), description="EM forward-backward passes at most"
    )
    gate_episodes: Annotated[int, Field(ge=1, le=1_000_000), INTEGRAL] = Field(
        1000, description="evaluation episodes of the gate (the same seeds for both policies)"
    )
    gate: bool = Field(True, description="publish only if the new policy is not worse than the current one")
    canary_pairs: Annotated[int, Field(ge=0, le=100_000), INTEGRAL] = Field(
        20,
        description="with promote: the new version first flies every other mission beside the current one until "
        "this many pairs of missions are complete, and is made current only if its mean capture time over them is "
        "not higher (otherwise rolled back, with an alert); 0 makes it current at once",
    )
    min_missions: Annotated[int, Field(ge=1, le=10_000_000), INTEGRAL] = Field(
        50,
        description="missions with usable records needed before a run may start (a model fitted on fewer is "
        "too uncertain to train on; the refusal says how many more)",
    )
    holdout: float = Field(
        0.25,
        gt=0.0,
        lt=1.0,
        allow_inf_nan=False,
        description="share of the missions held out of the fit: the gate compares the policies under a model "
        "estimated from these alone, which the new policy was not trained on",
    )
    em_pseudo_count: float | None = Field(
        None,
        ge=0.0,
        le=1e6,
        allow_inf_nan=False,
        description="Dirichlet prior of EM: expected transitions added to each entry of Gamma_hat's support "
        "(default: 1 on maps below 100 nodes, n / 15 up to 20 above: shared/learning/config.py em_prior)",
    )
    em_b0_pseudo_count: float | None = Field(
        None,
        ge=0.0,
        le=1e6,
        allow_inf_nan=False,
        description="Dirichlet prior of EM: expected starts added to every node of b0, so that no node is ruled "
        "out (default: as em_pseudo_count's)",
    )
    team_searcher: Literal["auto", "fhpe-sa", "none"] = Field(
        "auto",
        description="what the new version's robots fly together when their links allow (shared/core/team.py): "
        "fhpe-sa (the team's plan on the version's model and the collective belief), none (each robot on its own "
        "policy), or auto: fhpe-sa if, flown as a team on the gate's episodes, it captures sooner than the new "
        "policy alone (paired 95% CI below zero), else none",
    )
    team_episodes: Annotated[int, Field(ge=1, le=1_000_000), INTEGRAL] = Field(
        200, description="episodes of that comparison (the gate's first seeds; a team plans at every step)"
    )
    promote: bool = Field(True, description="make the new version current")
    speed: float | None = Field(
        None,
        ge=0.01,
        le=100.0,
        allow_inf_nan=False,
        description="retrain on the mission clock at this robot speed in m/s (docs/continuous-world.md, 'Training "
        "on the clock'): EM fits Gamma_hat per 1 s tick from the records' times (records without times are "
        "skipped), CE-PG trains on the map's travel times (its edge_lengths_m) and the gate evaluates on them; "
        "the new version flies on the clock. Default: the current version's, when it was trained on the clock; "
        "otherwise steps",
    )
    threads: Annotated[int, Field(ge=0, le=1024), INTEGRAL] = Field(
        train_config.TORCH_THREADS,
        description="torch threads in the training process (0: torch's default, one per core); "
        "the default is `mures train`'s",
    )

    @model_validator(mode="after")
    def _distinct(self) -> TrainingParams:
        if len(set(self.candidates or ())) != len(self.candidates or ()):
            raise ValueError("candidates must not repeat a method")
        return self

    def hyperparameters_of(self, method: str) -> dict[str, int | float | bool]:
        """The hyperparameters given for ``method`` (none: its documented defaults)."""
        return next((v for k, v in self.hyperparameters.items() if k == method), {})

    def methods(self) -> tuple[str, ...]:
        """The methods this run trains a team with."""
        if self.algorithm == "best":
            return tuple(self.candidates or DEFAULT_CANDIDATES)
        return (self.algorithm,)


def _die_with_parent(parent_pid: int) -> None:
    """A training process must not outlive its server (a kill -9 of the server included): Linux
    kills it when the server does (PR_SET_PDEATHSIG); elsewhere, and for a server that died before
    this line, a watchdog thread ends it within a second of the parent's end."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):
        pass

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(1.0)
        os._exit(1)

    if os.getppid() != parent_pid:
        os._exit(1)
    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def run_training(job: dict[str, Any], events: Any, cancel: Any, pause: Any) -> None:
    """The training process. Puts {"type": "progress"|"done"|"failed"|"cancelled"|"paused", ...}
    on ``events``; stops at its next check once ``cancel`` (the operator's) or ``pause`` (the
    server's stop: the run resumes at the next start) is set."""
    _die_with_parent(job["server_pid"])
    try:
        events.put({"type": "done", **_TrainingRun(job, events, cancel, pause).run()})
    except _Cancelled:
        events.put({"type": "cancelled"})
    except _Paused:
        events.put({"type": "paused"})
    except Exception as exc:  # reported to the operator, never crashes the server
        events.put({"type": "failed", "error": f"{type(exc).__name__}: {exc}", "trace": traceback.format_exc()})


class _Cancelled(Exception):
    pass


class _Paused(Exception):
    """The server is stopping: the run stops where it is and resumes at the next start."""


def measured_links(records: list[dict[str, Any]]) -> dict[str, Any]:
    """The fleet's network as its robots measured it, from the ``coordination`` of the records
    of robots that flew with a team searcher: the share of the teammates' observations lost
    (null: none flew with one), and the share of their robot-steps flown on the team's plan."""
    flown = heard = sent = coordinated = decided = 0
    for rec in records:
        c = rec.get("coordination") if isinstance(rec, dict) else None
        if not isinstance(c, dict) or c.get("team_searcher") is None:
            continue
        team, own = (c.get("team_steps") or 0) + (c.get("partial_steps") or 0), c.get("own_steps") or 0
        flown, coordinated, decided = flown + 1, coordinated + team, decided + team + own
        heard += c.get("observations_heard") or 0
        sent += c.get("observations_sent") or 0
    return {
        "records": flown,
        "link_loss": round(1.0 - heard / sent, 4) if sent else None,
        "coordinated_share": round(coordinated / decided, 4) if decided else None,
    }


def run_speed(params: TrainingParams, trained: tuple[float, float] | None) -> float | None:
    """The robot speed a run trains on travel times at: ``speed``, else the current version's
    (``trained``: its training's (speed, tick), None for a version trained in steps); None for a
    run in steps. A ValueError names a run that cannot: a version trained with another tick than the
    agents' 1 s (the body is valid: such a run fails at once, as one with an unknown hyperparameter
    does)."""
    from shared.core.clock import TICK_S

    speed = params.speed if params.speed is not None else (trained[0] if trained else None)
    if speed is None:
        return None
    if trained is not None and abs(trained[1] - TICK_S) > 1e-9:
        raise ValueError(f"the current version was trained with ticks of {trained[1]:g} s; the agents' are 1 s")
    return speed


class _TrainingRun:
    """One training run, in the training process: EM on the fleet's records, its teams trained
    in simulation under the estimated model (training_server/methods.py), the evaluation gate,
    the team decision, the new snapshot written to job["staging"]. Each step tells the server its
    progress (``say``) and stops at the next check once the run is cancelled or paused."""

    def __init__(self, job: dict[str, Any], events: Any, cancel: Any, pause: Any) -> None:
        import torch

        from shared.core.graph import graph_from_dict
        from shared.learning.team_snapshot import load_snapshot

        self.job, self.events, self.cancel, self.pause = job, events, cancel, pause
        self.folder = RunFolder(job["folder"])
        self.p = TrainingParams.model_validate(job["params"])
        if self.p.threads:
            torch.set_num_threads(self.p.threads)
        self.graph = graph_from_dict(job["graph"], "server map")
        self.current = load_snapshot(job["current_path"], self.graph)
        self.sensor = self.current.sensor
        self.clock = self._clock()
        self.t0 = time.perf_counter()

    def say(self, phase: str, **kw: Any) -> None:
        elapsed = round(time.perf_counter() - self.t0, 2)
        self.events.put({"type": "progress", "phase": phase, "elapsed_s": elapsed, **kw})

    def _clock(self) -> Any:
        """The run's travel times (``speed``, or the current version's), or None: steps."""
        from shared.core.clock import TICK_S, TravelTimes

        speed = run_speed(self.p, self.current.clock)
        return None if speed is None else TravelTimes.of(self.graph, speed, TICK_S)  # ValueError: no edge lengths

    def _on_clock(self, snap: Any) -> Any:
        """A team to evaluate on the run's travel times: one trained in steps gets its model made a
        tick's worth (shared/core/clock.py), one trained on the clock is as it is."""
        if self.clock is None or snap.clock is not None:
            return snap
        return replace(snap, model=self.clock.model(snap.model))

    def run(self) -> dict[str, Any]:
        for method in self.p.methods():  # a misnamed hyperparameter fails the run now, not after EM
            check_hyperparameters(method, self.p.hyperparameters_of(method))
        if self.current.general and set(self.p.team_sizes or ()) - {self.current.robots}:
            raise ValueError(
                "the current version is the general policy, which flies every team size: leave out team_sizes"
            )
        model, gate_model, em_info = self.models()
        self.check()
        N = self.current.robots
        trained = {m: self.train(m, N, model) for m in self.p.methods()}
        figures = self.evaluate(trained, gate_model, em_info["held_out"])
        chosen = min(trained, key=lambda m: (figures[m]["mean_capture_time"], self.p.methods().index(m)))
        passed = figures[chosen]["mean_capture_time"] <= figures["current"]["mean_capture_time"]
        sizes = sorted(set(self.p.team_sizes or ()) - {N})
        others: dict[int, TrainedTeam] = {}
        team: dict[str, Any] = {"team_searcher": None, "decided_by": "not decided: the run is gated out"}
        switching: dict[str, Any] = {}
        if passed or not self.p.gate:  # a gated-out run trains nothing more
            others = {k: self.train(chosen, k, model) for k in sizes}
            version = _version_data(trained[chosen], others)
            switching = self.switch_decision(version, gate_model)
            team = self.team_decision(replace(version, model=model), gate_model)
            self.write_snapshot(version, trained[chosen].summary, team["team_searcher"], switching.get("switch_to"))
        gate = {
            "current": figures["current"],
            "new": figures[chosen],
            "passed": passed,
            "enforced": self.p.gate,
            "model": f"EM on {em_info['held_out']} held-out missions" if em_info["held_out"] else "the uniform walk",
            "unit": "steps" if self.clock is None else f"ticks of {self.clock.tick_s:g} s",
        }
        return {
            "metrics": {
                "em": em_info,
                "algorithm": self.p.algorithm,
                "chosen": chosen,
                "train": _training_figures(trained[chosen]),
                "teams": [
                    {"method": t.method, "robots": t.robots, **_training_figures(t)}
                    for t in (*trained.values(), *others.values())
                ],
                "candidates": [{"method": "current", **figures["current"]}]
                + [{"method": m, **figures[m], "training": _training_figures(t)} for m, t in trained.items()],
                "team_sizes": sorted({N, *others}),
                "switching": switching,
                "team": team,
                "gate": gate,
                "wall_seconds": round(time.perf_counter() - self.t0, 2),
            },
            "passed": passed or not self.p.gate,
        }

    def models(self) -> tuple[Any, Any, dict[str, Any]]:
        """EM's model and the gate's (``estimate_models`` on the fleet's ``missions``), kept in the
        run's folder: a resumed run trains on the same model it started with."""
        saved = self.folder.load_models(self.graph)
        if saved is not None:
            models, info = saved
            self.links = info.pop("links")
            self.say("em", message="resuming: EM's models as the run estimated them before the restart")
            return models["fit"], models["gate"], info
        data, fit, held = self.missions()
        model, gate_model, em_info = self.estimate_models(data, fit, held)
        self.folder.save_models({"fit": model, "gate": gate_model}, {**em_info, "links": self.links})
        return model, gate_model, em_info

    def missions(self) -> tuple[Any, Any, Any]:
        """The fleet's missions (robots' positions and observations only), and their split into
        those EM fits and those held out for the gate."""
        from shared.engine.estimate import collect_missions
        from training_server.store import read_episode_records

        self.say("em", message="reading episode records")
        rows = read_episode_records(self.job["db"], self.job["fleet"], self.p.max_records)
        records = [json.loads(r) for r in rows]
        self.links = measured_links(records)
        tick_s = None if self.clock is None else self.clock.tick_s  # on the clock: EM per tick from the times
        data = collect_missions(enumerate(records), self.graph, fleet=self.job["fleet"], tick_s=tick_s)
        if len(data.length) == 0:
            raise ValueError(
                "no usable missions: fly some missions before training"
                + (" (on the clock only records with times count)" if tick_s is not None else "")
            )
        if data.impossible:
            self.say(
                "em",
                message=f"set aside {len(data.impossible)} missions no path of the target explains: "
                + ", ".join(data.impossible[:20])
                + (" ..." if len(data.impossible) > 20 else ""),
            )
        fit, held = split_missions(data, self.p.holdout, self.p.seed)
        self.say(
            "em", message=f"EM on {len(fit.length)} missions ({fit.used_records} records); {len(held.length)} held out"
        )
        return data, fit, held

    def estimate_models(self, data: Any, fit: Any, held: Any) -> tuple[Any, Any, dict[str, Any]]:
        """Step 1: EM's model from the missions fitted, the gate's from those held out (one mission
        cannot be split: the gate's model is then the prior alone, the uniform walk), and what
        the run's metrics record of them."""
        from shared.core.models import uniform_walk

        est = self._em(fit, "on the missions fitted")
        gate_est = self._em(held, "on the missions held out") if len(held.length) else None
        gate_model = gate_est.model if gate_est is not None else uniform_walk(self.graph)
        if gate_est is None and self.clock is not None:  # the prior per tick
            gate_model = self.clock.model(gate_model)
        em_info = {
            "missions": len(fit.length),
            "held_out": len(held.length),
            "records": fit.used_records,
            "iterations": est.iterations,
            "converged": est.converged,
            "gate_model_converged": gate_est.converged if gate_est is not None else None,
            "skipped": dict(data.skipped),
            "impossible_missions": data.impossible[:100],
            "prior": dict(zip(("pseudo_count", "b0_pseudo_count"), self.em_prior(), strict=True)),
            "per": "step" if self.clock is None else f"{self.clock.tick_s:g} s tick",
        }
        return est.model, gate_model, em_info

    def em_prior(self) -> tuple[float, float]:
        """EM's pseudo-counts on Gamma_hat's entries and on b0: the run's, else the map's default
        (shared/learning/config.py ``em_prior``)."""
        from shared.learning.config import em_prior

        default = em_prior(self.graph.n)
        given = (self.p.em_pseudo_count, self.p.em_b0_pseudo_count)
        return (default if given[0] is None else given[0], default if given[1] is None else given[1])

    def _em(self, missions: Any, which: str) -> Any:
        from shared.core.models import uniform_walk
        from shared.engine.estimate import em

        last = [0.0]  # the first pass of each fit is reported at once, then one every 0.25 s

        def em_progress(iteration: int, loglik: float) -> None:
            if iteration == 1 or time.perf_counter() - last[0] >= 0.25:
                last[0] = time.perf_counter()
                message = f"EM pass {iteration} {which} (log-likelihood {loglik:.1f})"
                self.say("em", iteration=iteration, max_iter=self.p.em_max_iter, message=message)
            self.check()

        pseudo_count, b0_pseudo_count = self.em_prior()
        return em(
            self.graph,
            missions,
            init=uniform_walk(self.graph),
            max_iter=self.p.em_max_iter,
            tol=1e-5,
            progress=em_progress,
            pseudo_count=pseudo_count,
            b0_pseudo_count=b0_pseudo_count,
        )

    def train(self, method: str, robots: int, model: Any) -> TrainedTeam:
        """A team of ``method`` for ``robots`` robots in simulation under the EM model: the one
        this run trained before a restart, else trained now (a MARL team from its checkpoint)."""
        done = self.folder.load_team(method, robots, self.graph)
        if done is not None:
            self.say("train", method=method, robots=robots, message=f"{method} for {robots} robots: trained before")
            return done
        episodes = self.p.episodes or max(256, round(default_episodes(method) * self.p.budget_fraction))
        if method in ("cepg", "pg"):  # whole batches
            batch = train_config.default("batch")
            planned = -(-episodes // batch) * batch
            rounded = f" ({episodes:,} asked, rounded up to whole batches of {batch})" if planned != episodes else ""
        else:
            planned, rounded = episodes, ""
        resumed = self.folder.checkpoint_dir(method, robots).exists()
        self.say(
            "train",
            method=method,
            robots=robots,
            episodes=0,
            total=planned,
            message=f"training {method} for {robots} robots, {planned:,} episodes{rounded}"
            + (" (resuming from its checkpoint)" if resumed else ""),
        )
        last = [0.0]

        def on_progress(point: dict[str, Any]) -> None:
            now = time.perf_counter()
            if now - last[0] >= 0.5 or point["episodes"] >= point["total"]:
                last[0] = now
                rate = float(point.get("episodes_per_second") or 0.0)
                left = max(0, int(point["total"]) - int(point["episodes"]))
                self.say(
                    "train",
                    method=method,
                    robots=robots,
                    episodes=int(point["episodes"]),
                    total=int(point["total"]),
                    mean_capture_time=round(float(point.get("mean_capture_time", float("nan"))), 3),
                    **({"eta_s": round(left / rate)} if rate > 0 else {}),  # this team's time left at its rate so far
                )

        team = train_team(
            method,
            robots,
            episodes,
            (self.graph, model, self.sensor),
            self.p,
            self.current,
            self.folder,
            on_progress,
            self.stopping,
            speed=None if self.clock is None else self.clock.speed,
        )
        if team is None:
            raise _Cancelled if self.cancel.is_set() else _Paused
        return team

    def check(self) -> None:
        """Stop here if the run is cancelled (``_Cancelled``) or the server is stopping (``_Paused``)."""
        if self.cancel.is_set():
            raise _Cancelled
        if self.pause.is_set():
            raise _Paused

    def stopping(self) -> bool:
        """Stop training: the run is cancelled, or the server is stopping (it resumes at the next start)."""
        return bool(self.cancel.is_set() or self.pause.is_set())

    def evaluate(self, trained: dict[str, TrainedTeam], gate_model: Any, held: int) -> dict[str, dict[str, Any]]:
        """The evaluation gate: the current version and each team trained on the same seeds under
        the held-out missions' model, which no new team was trained on (a model fitted on few
        missions flatters the policy trained on it; the prior keeps the held-out one cautious):
        mean capture time, its 95% CI, and the paired difference to the current version."""
        from shared.engine.evaluate import evaluate, mean_ci95
        from shared.learning.team_snapshot import PolicySearcher

        p, graph, sensor, N = self.p, self.graph, self.sensor, self.current.robots
        under = f"the model of {held} held-out missions" if held else "the uniform walk"
        teams = {"current": self._on_clock(self.current), **{m: t.snapshot for m, t in trained.items()}}
        self.say("gate", message=f"evaluating {', '.join(teams)} on {p.gate_episodes} episodes under {under}")
        figures, times = {}, {}
        for name, snap in teams.items():

            def team(seed: int, snap: Any = snap) -> PolicySearcher:
                return PolicySearcher(snap, graph, sensor, N, seed=seed)

            r = evaluate(
                graph, gate_model, sensor, N, team, episodes=p.gate_episodes, seed=p.seed + 1, clock=self.clock
            )
            summary = r.summary()
            times[name] = np.asarray(r.capture_time, dtype=np.float64)
            figures[name] = {k: summary[k] for k in ("mean_capture_time", "ci95", "censored_fraction", "episodes")}
            self.check()
        for name in trained:
            diff, half = mean_ci95(times[name] - times["current"])
            figures[name] |= {"paired_difference": round(diff, 3), "paired_ci95": round(half, 3)}
        return figures

    def switch_decision(self, version: Any, gate_model: Any) -> dict[str, Any]:
        """For each team size k < N the version holds a team for: whether its robots left switch
        to it when teammates drop out mid-mission (``TeamAgent.withdraw``). A network trained in
        a team of N searches its own part of the building and a team of k divides it otherwise, so
        a switch mid-mission can cost more than it gains (measured: benchmarks/team_switching.py).
        The robots fly their own policies on the gate's first ``team_episodes`` episodes under its
        model with N - k robots withdrawn (the last ones, at steps 2, 4, ...), switching and not;
        k is switched to only if switching captures sooner, its paired 95% CI below zero. A mission
        that starts with k robots flies the team built for k whatever this decides. On the clock the
        robots are their ``TimedTeamAgent``s on the travel times, withdrawn at steps' worth of ticks."""
        from shared.engine.evaluate import evaluate, mean_ci95
        from shared.engine.linked_team import LinkedTeamSearcher, linked_team

        N, p, snap = self.current.robots, self.p, version
        smaller = sorted(k for k in version.teams if k < N)
        if not smaller:
            return {}
        self.say(
            "gate", message=f"robots dropping out on {p.team_episodes} episodes: switching to teams {smaller} or not"
        )
        by_size, switch_to = {}, []
        step = 1 if self.clock is None else round(self.clock.ticks_per_step)  # on the clock: a step's worth of ticks
        for k in smaller:
            gone: list[int | None] = [None] * k + [2 * (N - k - i) * step for i in range(N - k)]
            times = {}
            for name, known in (("switch", True), ("keep", False)):

                def make(seed: int, known: bool = known) -> LinkedTeamSearcher:
                    return linked_team(snap, self.graph, N, seed, None, self.clock, known_withdrawals=known)

                r = evaluate(
                    self.graph,
                    gate_model,
                    self.sensor,
                    N,
                    make,
                    episodes=p.team_episodes,
                    seed=p.seed + 1,
                    withdraw_at=gone,
                    clock=self.clock,
                )
                times[name] = np.asarray(r.capture_time, dtype=np.float64)
                self.check()
            diff, half = mean_ci95(times["switch"] - times["keep"])
            if diff + half < 0:
                switch_to.append(k)
            by_size[str(k)] = {
                "withdrawn_at": gone,
                "switch_mean_capture_time": round(float(times["switch"].mean()), 3),
                "keep_mean_capture_time": round(float(times["keep"].mean()), 3),
                "paired_difference": round(diff, 3),
                "paired_ci95": round(half, 3),
            }
        return {"switch_to": switch_to, "episodes": p.team_episodes, "by_size": by_size}

    def team_decision(self, snap: Any, gate_model: Any) -> dict[str, Any]:
        """Step 4: whether the new version's robots fly the team's plan (FHPE-SA on the version's
        model) when their links allow. ``auto`` flies the new policy alone and as a team on the same
        episodes under the gate's model, over links that lose what the fleet's own links lost
        (``measured_links``; links up when no robot has flown with a team searcher yet), and takes
        the team only if it captures sooner, its paired 95% CI below zero. ``snap``: the new
        version (numpy, ``_version_data``) with the run's EM model as trained under."""
        from shared.engine.evaluate import evaluate, mean_ci95
        from shared.engine.linked_team import LinkedTeamSearcher, linked_team

        p = self.p
        if p.team_searcher == "none":
            return {"team_searcher": "none", "decided_by": "parameter", "links": self.links}
        loss = self.links["link_loss"] or 0.0
        self.say(
            "gate",
            message=f"flying the new policy alone and as a team on {p.team_episodes} episodes, "
            f"links losing {loss:.0%} of the messages",
        )
        times = {}
        for name, searcher in (("alone", None), ("team", "fhpe-sa")):

            def make(seed: int, searcher: str | None = searcher) -> LinkedTeamSearcher:
                return linked_team(snap, self.graph, snap.robots, seed, searcher, self.clock, link_loss=loss)

            r = evaluate(
                self.graph,
                gate_model,
                self.sensor,
                snap.robots,
                make,
                episodes=p.team_episodes,
                seed=p.seed + 1,
                clock=self.clock,
            )
            times[name] = np.asarray(r.capture_time, dtype=np.float64)
        diff, half = mean_ci95(times["team"] - times["alone"])
        better = diff + half < 0
        chosen = p.team_searcher if p.team_searcher != "auto" else ("fhpe-sa" if better else "none")
        return {
            "team_searcher": chosen,
            "decided_by": "comparison" if p.team_searcher == "auto" else "parameter",
            "episodes": p.team_episodes,
            "links": self.links,
            "alone_mean_capture_time": round(float(times["alone"].mean()), 3),
            "team_mean_capture_time": round(float(times["team"].mean()), 3),
            "paired_difference": round(diff, 3),
            "paired_ci95": round(half, 3),
        }

    def write_snapshot(
        self, version: Any, summary: dict[str, Any], team_searcher: str, switch_to: list[int] | None
    ) -> None:
        """The new version's snapshot (``_version_data``: the chosen method's team for N and its
        teams for the other team sizes) with the team searcher and the switches decided."""
        from shared.core.snapshot_format import write_snapshot

        out = Path(self.job["staging"])
        shutil.rmtree(out, ignore_errors=True)
        meta = version.meta
        config = {**meta["training"], "parent_version": self.job["parent"], "run_algorithm": self.p.algorithm}
        write_snapshot(
            out,
            self.graph,
            version.weights,
            version.model,
            self.sensor,
            meta["variant"],
            meta["beta"],
            config,
            summary,
            algorithm=meta.get("algorithm", "cepg"),
            team_searcher=team_searcher,
            teams=version.teams,
            switch_to=switch_to,
            robots=version.robots,
        )


def _version_data(new: TrainedTeam, others: dict[int, TrainedTeam]) -> Any:
    """The new version in numpy (shared.core.snapshot_format.SnapshotData): the chosen team for N
    with its model and sensor, and the teams for the other team sizes, as agents will fly them."""
    from shared.core.snapshot_format import SnapshotData
    from shared.learning.team_snapshot import policy_weights

    teams = {k: policy_weights(t.snapshot.policy) for k, t in others.items()}
    snap = new.snapshot
    return SnapshotData(
        meta=dict(snap.meta), weights=policy_weights(snap.policy), model=snap.model, sensor=snap.sensor, teams=teams
    )


def _training_figures(team: TrainedTeam) -> dict[str, Any]:
    """What a run's metrics say of a team's training (and ``resumed``: where a restart resumed it)."""
    keys = ("episodes", "env_steps", "wall_seconds", "episodes_per_second", "resumed")
    return {k: team.summary[k] for k in keys if k in team.summary}


def split_missions(data: Any, holdout: float, seed: int) -> tuple[Any, Any]:
    """(fit, held out): the missions of ``data`` (an estimate.MissionData) dealt at random (seeded)
    into two sets, ``holdout`` of them (at least one, at most all but one) held out."""
    M = len(data.length)
    order = np.random.default_rng(seed).permutation(M)
    k = min(M - 1, max(1, round(holdout * M)))  # none of a single mission
    return data.subset(order[k:]), data.subset(order[:k])


CURVE_POINTS = 400  # a run's learning curve keeps at most this many points
PAUSE_WAIT_S = 60.0  # how long a stopping server waits for its training process to pause (a MARL checkpoint)


class Supervisor:
    """Runs queued training runs one at a time, each in its own process."""

    def __init__(self, server: Any) -> None:
        self.server = server
        self.ctx = mp.get_context("spawn")
        self.queue: queue.Queue[str] = queue.Queue()
        self.cancels: dict[str, Any] = {}
        self.lock = threading.Lock()
        self.stopping = threading.Event()
        self.pause = self.ctx.Event()  # the server is stopping: the running run pauses, to resume at the next start
        self.thread = threading.Thread(target=self._loop, name="training-supervisor", daemon=True)
        self.current_proc: Any = None

    def start(self) -> None:
        self.thread.start()

    def submit(self, run_id: str) -> None:
        with self.lock:
            self.cancels[run_id] = self.ctx.Event()
        self.queue.put(run_id)

    def cancel(self, run_id: str) -> bool:
        with self.lock:
            ev = self.cancels.get(run_id)
        if ev is None:
            return False
        ev.set()
        return True

    def stop(self) -> None:
        """The server is stopping: the running run pauses (a MARL team saves its checkpoint) and
        stays running in the store, as do the queued ones; the next start resumes them
        (``resume_interrupted``)."""
        self.stopping.set()
        self.pause.set()
        self.queue.put("")
        proc = self.current_proc
        if proc is not None:
            proc.join(PAUSE_WAIT_S)
            if proc.is_alive():
                proc.kill()
        self.thread.join(15)

    def resume_interrupted(self) -> list[tuple[str, str]]:
        """At the server's start: the runs a previous server process left queued or running go on
        (queued again, in the order they were created; a run's folder holds what it had done),
        except those an operator had cancelled. Returns (run, status)."""
        out = self.server.store.requeue_interrupted_runs()
        resumed = [run_id for run_id, status in out if status == "queued"]
        for stale in (self.server.data_dir / "runs").glob("*"):  # folders of runs that ended meanwhile
            if stale.name not in resumed:
                shutil.rmtree(stale, ignore_errors=True)
        for run_id in resumed:
            self.submit(run_id)
        return out

    def _loop(self) -> None:
        while not self.stopping.is_set():
            run_id = self.queue.get()
            if not run_id or self.stopping.is_set():
                continue
            try:
                self._run(run_id)
            except Exception:
                log.exception("training run %s: supervisor error", run_id)
                self.server.store.update_run(run_id, status="failed", finished=time.time(), error="server error")
            finally:
                with self.lock:
                    self.cancels.pop(run_id, None)

    def _run(self, run_id: str) -> None:
        srv = self.server
        store = srv.store
        with self.lock:
            cancel = self.cancels[run_id]
        run = store.get_run(run_id)
        assert run is not None
        if run["status"] != "queued":  # cancelled while it waited (the store says so already)
            return
        if cancel.is_set():
            store.update_run(run_id, status="cancelled", finished=time.time())
            return
        folder = srv.data_dir / "runs" / run_id
        folder.mkdir(parents=True, exist_ok=True)
        started = folder / "run.json"  # the version the run started from: a resumed run goes on from it
        resumed = started.is_file()
        if resumed:
            parent = int(json.loads(started.read_text(encoding="utf-8"))["parent"])
        else:
            parent = srv.current_version()
            started.write_text(json.dumps({"parent": parent}), encoding="utf-8")
        staging = srv.data_dir / "staging" / run_id
        job = {
            "folder": str(folder),
            "params": run["params"],
            "graph": srv.graph.to_json(),
            "db": store.url,
            "server_pid": os.getpid(),
            "fleet": srv.fleet,
            "current_path": str(srv.snapshot_dir(parent)),
            "parent": parent,
            "staging": str(staging),
        }
        events = self.ctx.Queue()
        proc = self.ctx.Process(
            target=run_training, args=(job, events, cancel, self.pause), name=f"train-{run_id}", daemon=True
        )
        if resumed:
            store.update_run(run_id, status="running", progress={"phase": "starting", "message": "resuming"})
        else:
            store.update_run(run_id, status="running", started=time.time(), progress={"phase": "starting"})
        log.info(
            "training run %s %s from version %s: %s",
            run_id,
            "resumed" if resumed else "started",
            parent,
            json.dumps(run["params"]),
        )
        self.current_proc = proc
        proc.start()
        result: dict[str, Any] | None = None
        curve: list[list[float]] = []  # the learning curve of the team in training: [episodes, mean capture time]
        training: tuple[Any, Any] | None = None  # (method, robots) of that team
        while result is None:
            try:
                ev = events.get(timeout=0.5)
            except queue.Empty:
                if not proc.is_alive():
                    try:  # the last message may still be in the pipe
                        ev = events.get(timeout=1.0)
                    except queue.Empty:
                        ev = {"type": "failed", "error": f"training process died (exit code {proc.exitcode})"}
                else:
                    continue
            if ev["type"] == "progress":
                point = {k: v for k, v in ev.items() if k != "type"}
                if isinstance(point.get("mean_capture_time"), float) and not math.isfinite(point["mean_capture_time"]):
                    del point["mean_capture_time"]  # no finished episode in the batch yet: no figure
                if point.get("phase") == "train" and (point.get("method"), point.get("robots")) != training:
                    training, curve = (point.get("method"), point.get("robots")), []  # the next team's curve
                if point.get("phase") == "train" and isinstance(point.get("mean_capture_time"), float):
                    curve.append([point["episodes"], point["mean_capture_time"]])
                    if len(curve) > CURVE_POINTS:  # long runs: every other point
                        curve[:] = curve[::2]
                store.update_run(run_id, progress={**point, "curve": curve})
            else:
                result = ev
        proc.join(10)
        self.current_proc = None
        now = time.time()
        if result["type"] == "paused" or (result["type"] == "failed" and self.pause.is_set()):
            store.update_run(
                run_id, progress={"phase": "paused", "message": "server stopping; resumes at its next start"}
            )
            log.info("training run %s paused by the server's stop; it resumes at the next start", run_id)
            return

        def finish(status: str, phase: str, **fields: Any) -> None:
            """The run's end: its staging directory removed first (whoever reads the status sees the
            run's files gone), then its status and last phase, the learning curve kept."""
            shutil.rmtree(staging, ignore_errors=True)
            store.update_run(run_id, status=status, finished=now, progress={"phase": phase, "curve": curve}, **fields)

        if result["type"] == "cancelled":
            finish("cancelled", "cancelled")
            log.info("training run %s cancelled", run_id)
        elif result["type"] == "failed":
            finish("failed", "failed", error=result["error"])
            log.warning("training run %s failed: %s", run_id, result["error"])
        elif not result["passed"]:
            g = result["metrics"]["gate"]
            finish(
                "failed",
                "gated out",
                metrics=result["metrics"],
                error=f"evaluation gate: new policy {g['new']['mean_capture_time']:.2f} {g.get('unit', 'steps')}, "
                f"current {g['current']['mean_capture_time']:.2f}; current policy kept",
            )
            log.info("training run %s did not pass the gate; version %s stays current", run_id, parent)
        else:
            params = TrainingParams.model_validate(run["params"])
            staged = params.promote and params.canary_pairs > 0
            version = srv.publish_version(
                staging, parent=parent, run_id=run_id, metrics=result["metrics"], promote=params.promote and not staged
            )
            if staged:
                srv.start_canary(version, parent, run_id, params.canary_pairs)
            finish("succeeded", "canary" if staged else "done", metrics=result["metrics"], version=version)
            log.info("training run %s succeeded: version %d%s", run_id, version, " (on trial)" * staged)
        RunFolder(folder).remove()
