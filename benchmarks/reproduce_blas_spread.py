"""Spread of the quoted figures over OpenBLAS settings on this machine.

Reruns ``benchmarks/reproduce_figures.py GROUP --json`` in fresh processes under each
variant (thread count, forced OpenBLAS core type) and prints, per figure, the minimum
and maximum over the variants (strings: whether every variant gave the same text)::

    python benchmarks/reproduce_blas_spread.py seed-ocp room crane boundary delay --out spread.json

Variants: OPENBLAS_NUM_THREADS=1 and 2 (auto core type), and OPENBLAS_CORETYPE=Haswell /
SandyBridge / Prescott with one thread.  The core type OpenBLAS actually selected is read
back from NumPy's OpenBLAS (``*_get_corename``) and recorded, since an unknown name is
silently replaced (on this build "Prescott" selects the "Katmai" kernels).  MKL is not
installed; NumPy/SciPy link their own OpenBLAS (scipy-openblas 0.3.31, DYNAMIC_ARCH).
CasADi/IPOPT use their own bundled linear algebra (MUMPS), not these settings.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
VARIANTS = {
    "threads1": {"OPENBLAS_NUM_THREADS": "1"},
    "threads2": {"OPENBLAS_NUM_THREADS": "2"},
    "Haswell": {"OPENBLAS_NUM_THREADS": "1", "OPENBLAS_CORETYPE": "Haswell"},
    "SandyBridge": {"OPENBLAS_NUM_THREADS": "1", "OPENBLAS_CORETYPE": "SandyBridge"},
    "Prescott": {"OPENBLAS_NUM_THREADS": "1", "OPENBLAS_CORETYPE": "Prescott"},
}
CORENAME = (
    "import ctypes, glob, os, numpy\n"
    "d = os.path.join(os.path.dirname(numpy.__file__), '..', 'numpy.libs')\n"
    "names = []\n"
    "for f in glob.glob(os.path.join(d, '*openblas*')):\n"
    "    lib = ctypes.CDLL(f)\n"
    "    for s in ('scipy_openblas_get_corename64_', 'openblas_get_corename64_', 'openblas_get_corename'):\n"
    "        if hasattr(lib, s):\n"
    "            fn = getattr(lib, s); fn.restype = ctypes.c_char_p; names.append(fn().decode()); break\n"
    "print(','.join(names) or 'unknown')\n"
)


def _env(extra: dict) -> dict:
    env = {
        k: v
        for k, v in os.environ.items()
        if not k.startswith(("OPENBLAS_", "OMP_NUM_THREADS"))
    }
    env.setdefault("PYTHONPATH", str(ROOT / "src"))
    env["MPLBACKEND"] = "Agg"
    env.update(extra)
    return env


def corename(extra: dict) -> str:
    return subprocess.run(
        [sys.executable, "-c", CORENAME],
        check=False,
        env=_env(extra),
        capture_output=True,
        text=True,
    ).stdout.strip()


def run_group(group: str, extra: dict) -> dict:
    p = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "reproduce_figures.py"), group, "--json"],
                       check=False, cwd=ROOT, env=_env(extra), capture_output=True, text=True)  # fmt: skip
    if p.returncode != 0:
        return {"error": p.stderr[-500:]}
    return json.loads(p.stdout.strip().splitlines()[-1])


def spread(results: dict) -> dict:
    """{variant: {key: value}} -> {key: (min, max) or (text, all_equal)}."""
    keys = sorted({k for r in results.values() for k in r if k != "error"})
    out = {}
    for k in keys:
        vals = [r[k] for r in results.values() if k in r]
        if all(isinstance(v, (int, float)) for v in vals):
            out[k] = {"min": min(vals), "max": max(vals), "n": len(vals)}
        else:
            out[k] = {"values": sorted(set(map(str, vals))), "n": len(vals)}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("groups", nargs="+")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--out", default=None, help="write raw results and spread as JSON")
    a = ap.parse_args(argv)
    raw: dict = {"corename": {}, "groups": {}}
    for v in a.variants.split(","):
        raw["corename"][v] = corename(VARIANTS[v])
    for g in a.groups:
        res = {}
        for v in a.variants.split(","):
            res[v] = run_group(g, VARIANTS[v])
            print(
                f"# {g} / {v} (core {raw['corename'][v]}): {len(res[v])} figures",
                file=sys.stderr,
                flush=True,
            )
        raw["groups"][g] = {"results": res, "spread": spread(res)}
        for k, s in raw["groups"][g]["spread"].items():
            if "min" in s:
                same = (
                    "identical"
                    if s["min"] == s["max"]
                    else f"rel spread {abs(s['max'] - s['min']) / max(abs(s['max']), 1e-300):.1e}"
                )
                print(
                    f"{k:60s} min {s['min']:.10g}  max {s['max']:.10g}  ({same}, n={s['n']})"
                )
            else:
                print(f"{k:60s} {' | '.join(s['values'])}  (n={s['n']})")
        if a.out:
            Path(a.out).write_text(json.dumps(raw, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
