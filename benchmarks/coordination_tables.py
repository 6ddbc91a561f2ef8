"""The tables of docs/coordination.md, from the records benchmarks/coordination.py and
benchmarks/model_error.py wrote in results/coordination/.

    python benchmarks/coordination_tables.py
"""

from __future__ import annotations

import json
from pathlib import Path

OUT = Path("results/coordination")


def _cell(r: dict, key: str) -> str:
    d = r.get(f"diff_to_{key}")
    return "—" if d is None else f"{d:+.2f} ± {r[f'diff_to_{key}_ci95']:.2f}"


def _share(r: dict) -> str:
    if r.get("share_complete") is None:
        return "—"
    return f"{r['share_complete']:.2f} / {r['share_partial']:.2f} / {r['share_own']:.2f}"


def _pick(rows: list[dict], label: str, **where) -> dict | None:
    """The first row of ``label`` whose fields hold ``where``."""
    for r in rows:
        if r["searcher"] == label and all(r.get(k) == v for k, v in where.items()):
            return r
    return None


def summary() -> None:
    """Links up, per map and team size: the informed planner, CE-PG alone, the best learners alone,
    the team on the fleet's model of 2,000 missions."""
    print("| map | N | FHPE-SA informed | CE-PG alone | MASAC alone | PG alone | team, model of 2,000 missions "
          "| team vs CE-PG alone | team vs informed | CE-PG alone, 1500 episodes |")  # fmt: skip
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for path in sorted(OUT.glob("*-N[0-9].json")):
        rec = json.loads(path.read_text())
        rows = rec["rows"]

        def mean(r: dict | None) -> str:
            return "—" if r is None else f"{r['mean_capture_time']:.2f} ± {r['ci95_halfwidth']:.2f}"

        team = _pick(rows, "team fhpe-sa", fleet_missions=2000, link_loss=0.0, link_delay=0, robots=rec["robots"])
        team = team if team and "trained_for" not in team and "withdrawn" not in team else None
        alone = next(r for r in rows if r["searcher"] == "cepg alone" and not r.get("own_row"))
        long = next((r for r in rows if r.get("own_row")), None)
        print(
            f"| {rec['map']} | {rec['robots']} | {mean(rows[0])} | {mean(alone)} | {mean(_pick(rows, 'masac alone'))} "
            f"| {mean(_pick(rows, 'beta1.0 alone'))} | {mean(team)} | {_cell(team, 'cepg_alone') if team else '—'} "
            f"| {_cell(team, 'fhpe_sa_informed') if team else '—'} | {mean(long)} |"
        )


def detail(name: str) -> None:
    """Every row of one record, after the command that wrote it."""
    rec = json.loads((OUT / name).read_text())
    print(f"`{rec['command']}` ({rec['episodes']} paired episodes, seed {rec['seed']}, {rec['wall_seconds']:.0f} s)")
    print()
    table(rec)
    print()


def table(rec: dict) -> None:
    """A benchmarks/coordination.py record's rows as a Markdown table."""
    print("| searcher | robots | setting | fleet missions (Gamma_hat row TV) | capture time | vs CE-PG alone "
          "| vs FHPE-SA informed | robot-steps complete / partial / own |")  # fmt: skip
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rec["rows"]:
        setting = ", ".join(
            f"{k.replace('_', ' ')} {r[k]}"
            for k in ("link_loss", "link_delay", "withdrawn", "trained_for")
            if r.get(k) not in (None, 0, 0.0)
        )
        if r.get("own_row"):
            setting = f"{r['episodes']} episodes (not paired)"
        missions = r.get("fleet_missions", "—")
        if r.get("gamma_row_tv") is not None:
            missions = f"{missions} ({r['gamma_row_tv']:.3f})"
        label = r["searcher"].replace("beta1.0", "pg")
        print(
            f"| {label} | {r['robots']} | {setting or '—'} | {missions} "
            f"| {r['mean_capture_time']:.2f} ± {r['ci95_halfwidth']:.2f} | {_cell(r, 'cepg_alone')} "
            f"| {_cell(r, 'fhpe_sa_informed')} | {_share(r)} |"
        )


def model_error(name: str) -> None:
    rec = json.loads((OUT / name).read_text())
    print(f"`{rec['command']}` ({rec['episodes']} paired episodes, target {rec['target']})")
    print()
    print("| searcher | fleet missions | pseudo-count | Gamma_hat row TV | b0 TV | capture time | vs CE-PG alone "
          "| vs FHPE-SA informed |")  # fmt: skip
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rec["rows"]:
        print(
            f"| {r['searcher']} | {r.get('fleet_missions', '—')} | {r.get('pseudo_count', '—')} "
            f"| {r.get('gamma_row_tv', '—')} | {r.get('b0_tv', '—')} "
            f"| {r['mean_capture_time']:.2f} ± {r['ci95_halfwidth']:.2f} | {_cell(r, 'cepg_alone')} "
            f"| {_cell(r, 'fhpe_sa_informed')} |"
        )
    print()


def main() -> None:
    summary()
    print()
    for path in sorted(OUT.glob("*-N[0-9].json")):
        print(f"### {path.stem}")
        print()
        detail(path.name)
    for path in sorted(OUT.glob("model-error-*.json")):
        print(f"### {path.stem}")
        print()
        model_error(path.name)


if __name__ == "__main__":
    main()
