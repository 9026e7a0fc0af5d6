"""The demo's closing summary on the terminal."""

from __future__ import annotations


def _f(v, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


def print_summary(m: dict, cfg) -> None:
    print(f"fused map v{m['fused_version']}: {m['fused_segments']} segments", end="")
    if "fused_precision" in m:
        print(f", precision {m['fused_precision']:.3f}, completeness {m['fused_completeness']:.3f}", end="")
    if "fused_precision_fit" in m:
        p, c = m["fused_precision_fit"], m["fused_completeness_fit"]
        print(f" (fitted frames {p:.3f} / {c:.3f})", end="")
    print()
    for name, r in m["robots"].items():
        line = f"  {name}: {r['status']}, first merge {_f(r.get('time_to_first_merge_s'), '.1f')} s"
        if "transform_error_m" in r:
            line += f", transform error {r['transform_error_m']:.3f} m / {r['transform_error_deg']:.2f}°"
        if "transform_error_fit_m" in r:
            fit_m, fit_deg = r["transform_error_fit_m"], r["transform_error_fit_deg"]
            line += f" (fitted frames {fit_m:.3f} m / {fit_deg:.2f}°)"
        if "ate_m" in r:
            line += f", ATE {r['ate_m']:.3f} m (SLAM alone {r['ate_slam_m']:.3f})"
        bps = r.get("bytes_per_s")
        if bps:
            line += f", {bps['total'] / 1000:.1f} kB/s"
        print(line)
    if "relations" in m:
        e = m["relations"]
        print(
            f"relations error (global poses): {e['trans_mean_m']:.3f} m, "
            f"{e['rot_mean_deg']:.2f}° (n={e['n']} of {m['relations_total']} relations: both ends merged)"
        )
    if "relations_across" in m:
        e = m["relations_across"]
        print(
            f"  across pieces: {e['trans_mean_m']:.3f} m, {e['rot_mean_deg']:.2f}° "
            f"(n={e['n']}: one end in each of two pieces)"
        )
    half = m.get("half_time")
    if half is not None:
        line = f"at half time ({half['at_s']:.0f} s, fused v{half['fused_version']}): "
        line += f"{len(half['merged'])} pieces placed"
        if "relations" in half:
            e = half["relations"]
            line += f", relations error {e['trans_mean_m']:.3f} m, {e['rot_mean_deg']:.2f}° (n={e['n']})"
        print(line)
    if m.get("wrong_merges"):
        print(f"WRONG MERGES: {m['wrong_merges']}")
    print(f"wrote {cfg.out}/ in {m['wall_time_s']:.0f} s")
