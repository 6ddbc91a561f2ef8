"""Resumable training of the MARL baselines: a run's whole state in a directory, written every
``every_s`` seconds of training and when a stop is asked, so that a run that is killed (a machine
handed back, a job's time limit) or stopped continues from its last checkpoint. A resumed run gives
the same numbers, bit for bit, as one never interrupted (tests/test_marl.py): what is saved is
everything the next step depends on (networks, optimisers, replay buffers, the episodes in
flight and their beliefs, every random generator, the collector's carried step, the budget's
bookkeeping and learning curve).

Layout of the directory DIR:
    state.pt         torch.save of {"format", "identity", "saved_at", "state": {name: ...}}
    buffers/NAME/    each replay buffer, by TorchRL's ``ReplayBuffer.dumps`` (memory-mapped)
A checkpoint is written to DIR.new and then put in DIR's place (the previous one is kept as
DIR.old until then), so a run killed while writing leaves the previous checkpoint whole.

A checkpoint belongs to one run: its ``identity`` (algorithm, hyperparameters, configuration,
map, sensor, target model) must equal the resuming run's, or loading refuses with a ValueError
that names what differs.
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torchrl.collectors import Collector
from torchrl.data import ReplayBuffer

FORMAT = 1
STATE_FILE = "state.pt"


def _state(obj: Any) -> Any:
    """The saved form of one tracked object (not a replay buffer: those are dumped to files)."""
    if isinstance(obj, torch.Generator):
        return obj.get_state()
    if isinstance(obj, Collector):
        # the step carried from one batch to the next (the collector's own state_dict leaves it
        # out: "runtime environment state is not generally serializable"; ours is a TensorDict)
        # and its counters
        sd = obj.state_dict()
        return {"carrier": obj._carrier.clone(), **{k: sd[k] for k in ("frames", "iter", "traj_pool") if k in sd}}
    if hasattr(obj, "state_dict"):  # nn.Module, Optimizer, EnvCore, StateHolder
        return obj.state_dict()
    raise TypeError(f"cannot checkpoint a {type(obj).__name__}")


def _restore(obj: Any, state: Any) -> None:
    if isinstance(obj, torch.Generator):
        obj.set_state(state)
    elif isinstance(obj, Collector):
        obj.load_state_dict({k: v for k, v in state.items() if k != "carrier"}, strict=False)
        obj._carrier.update(state["carrier"])
    else:
        obj.load_state_dict(state)


def _differences(a: dict[str, Any], b: dict[str, Any], prefix: str = "") -> list[tuple[str, Any, Any]]:
    """(dotted key, a's value, b's value) for every entry that differs, nested dicts entry by entry."""
    out = []
    for k in sorted(set(a) | set(b)):
        x, y = a.get(k), b.get(k)
        if isinstance(x, dict) and isinstance(y, dict):
            out += _differences(x, y, f"{prefix}{k}.")
        elif x != y:
            out.append((f"{prefix}{k}", x, y))
    return out


def _last_whole(path: Path) -> Path | None:
    """The directory holding a run's last whole checkpoint: DIR, or DIR.old where a save was cut off
    between putting the new one in place and removing the old; None where there is none."""
    for p in (path, path.with_name(path.name + ".old")):
        if (p / STATE_FILE).is_file():
            return p
    return None


def saved_episodes(path: str | Path) -> int | None:
    """How many training episodes the run whose checkpoint directory is ``path`` had done at its
    last checkpoint, read without restoring anything; None where there is no readable checkpoint
    (`mures experiment --plan` prices a team's remaining training by it)."""
    where = _last_whole(Path(path))
    if where is None:
        return None
    try:
        saved = torch.load(where / STATE_FILE, weights_only=False, map_location="cpu")
        return int(saved["state"]["run"]["episodes"])
    except Exception:  # a truncated or foreign file: loading it would say what is wrong
        return None


class StateHolder:
    """Plain values (counters, lists) under a name, saved and restored through two functions."""

    def __init__(self, get: Callable[[], dict[str, Any]], put: Callable[[dict[str, Any]], None]) -> None:
        self.state_dict, self.load_state_dict = get, put


class Checkpointer:
    """A run's checkpoint directory (module docstring). ``track(name, obj)`` registers what is
    saved: torch modules and optimisers, generators, replay buffers, a TorchRL collector, the
    environment's core, ``StateHolder``s. ``load()`` restores them all (True) or finds no
    checkpoint (False); ``save()`` writes them; ``due()`` says whether ``every_s`` seconds have
    passed since the last save (or the start); ``remove()`` deletes the directory."""

    def __init__(self, path: str | Path, identity: dict[str, Any], every_s: float = 600.0) -> None:
        if every_s < 0:
            raise ValueError(f"checkpoint interval must be >= 0 seconds, got {every_s}")
        self.path = Path(path)
        foreign = self.path.exists() and not (self.path / STATE_FILE).is_file()
        if foreign and (not self.path.is_dir() or any(self.path.iterdir())):
            raise ValueError(f"{self.path} exists and is not a checkpoint directory; refusing to replace it")
        self.identity, self.every_s = identity, float(every_s)
        self.objects: dict[str, Any] = {}
        self.last = time.perf_counter()
        self.saves = 0

    def track(self, name: str, obj: Any) -> None:
        if name in self.objects:
            raise ValueError(f"{name!r} is tracked already")
        self.objects[name] = obj

    def due(self) -> bool:
        return time.perf_counter() - self.last >= self.every_s

    def exists(self) -> bool:
        return _last_whole(self.path) is not None

    def load(self) -> bool:
        where = _last_whole(self.path)
        if where is None:
            return False
        try:
            saved = torch.load(where / STATE_FILE, weights_only=False, map_location="cpu")
        except Exception as exc:  # a truncated or foreign file
            raise ValueError(f"{where / STATE_FILE} is not a readable checkpoint: {exc}") from None
        if not isinstance(saved, dict) or saved.get("format") != FORMAT:
            raise ValueError(f"{where / STATE_FILE}: not a checkpoint of format {FORMAT}")
        differs = _differences(saved["identity"], self.identity)
        if differs:
            k, there, here = differs[0]
            raise ValueError(
                f"{where} holds a checkpoint of another run ({k}: {there!r} there, {here!r} here); "
                "remove it or name another checkpoint directory"
            )
        missing = sorted(set(self.objects) - set(saved["state"]) - set(self._buffers()))
        if missing:
            raise ValueError(f"{where / STATE_FILE} lacks {', '.join(missing)}")
        for name, obj in self.objects.items():
            if isinstance(obj, ReplayBuffer):
                folder = where / "buffers" / name
                if folder.is_dir():  # an empty buffer is not dumped
                    obj.loads(folder)
            else:
                _restore(obj, saved["state"][name])
        self.last = time.perf_counter()
        return True

    def _buffers(self) -> list[str]:
        return [k for k, v in self.objects.items() if isinstance(v, ReplayBuffer)]

    def save(self) -> None:
        new = self.path.with_name(self.path.name + ".new")
        old = self.path.with_name(self.path.name + ".old")
        shutil.rmtree(new, ignore_errors=True)
        (new / "buffers").mkdir(parents=True)
        state = {k: _state(v) for k, v in self.objects.items() if not isinstance(v, ReplayBuffer)}
        for name in self._buffers():
            if len(self.objects[name]) > 0:
                self.objects[name].dumps(new / "buffers" / name)
        payload = {"format": FORMAT, "identity": self.identity, "saved_at": time.time(), "state": state}
        torch.save(payload, new / STATE_FILE)
        if self.path.exists():
            shutil.rmtree(old, ignore_errors=True)
            self.path.rename(old)
        new.rename(self.path)
        shutil.rmtree(old, ignore_errors=True)
        self.last = time.perf_counter()
        self.saves += 1

    def remove(self) -> None:
        """Delete the checkpoint (DIR and DIR.old if they hold one, a cut-off DIR.new)."""
        for suffix in ("", ".new", ".old"):
            p = self.path.with_name(self.path.name + suffix)
            if suffix == ".new" or (p / STATE_FILE).is_file():
                shutil.rmtree(p, ignore_errors=True)
