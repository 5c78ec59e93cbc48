"""Probe (not a fix): does a slow tail that cannot coincide with the fast one end the straggler
fits? Runs ``experiments/straggler_fits.py`` with the problem's coordinates patched in this
process only: the slow tail's time constant becomes ``pulse_tail_s x (1 + exp(w))`` (the
equal-tails branch of the two-tail model's singular set moved to ``w -> -inf``). **Simulated**
data, as straggler_fits.py. Arguments are straggler_fits.py's.

    TOFJAX_PROGRAM_STORE=0 python experiments/straggler_tail_ratio.py --seeds 2000 2011 2031 2033 2014 2017 \\
        --variants default --diagnose -1 --out docs/results/straggler_tail_ratio.json
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def patch():
    import jax.numpy as jnp

    from tofjax.fit._problem import CalibrationProblem

    phys0, pack0 = CalibrationProblem.physical, CalibrationProblem.pack_jax

    def physical(self, u):
        out = phys0(self, u)
        if "pulse_slow_tail_s" in u and "pulse_tail_s" in u:
            out["pulse_slow_tail_s"] = out["pulse_tail_s"] * (1.0 + jnp.exp(u["pulse_slow_tail_s"]))
        return out

    def pack_jax(self, params, names, values=None):
        u = pack0(self, params, names, values)
        if "pulse_slow_tail_s" in u and "pulse_tail_s" in u:
            values = values or {}

            def get(k):
                return jnp.asarray(values[k] if k in values else getattr(params, k), jnp.result_type(float))

            u["pulse_slow_tail_s"] = jnp.log(jnp.maximum(get("pulse_slow_tail_s") / get("pulse_tail_s") - 1.0, 1e-9))
        return u

    CalibrationProblem.physical, CalibrationProblem.pack_jax = physical, pack_jax


if __name__ == "__main__":
    import jax

    jax.config.update("jax_enable_x64", True)
    patch()
    import straggler_fits

    rc = straggler_fits.main(sys.argv[1:])
    import json

    args = sys.argv[1:]
    out = Path(args[args.index("--out") + 1]) if "--out" in args else Path("docs/results/straggler_fits.json")
    out = out if out.is_absolute() else straggler_fits.ROOT / out
    d = json.loads(out.read_text())
    d["command"] = "TOFJAX_PROGRAM_STORE=0 python experiments/straggler_tail_ratio.py " + " ".join(args)
    d["probe"] = "slow tail's time constant = pulse_tail_s x (1 + exp(w)), patched in the process (not in tofjax)"
    out.write_text(json.dumps(d, indent=1) + "\n")
    sys.exit(rc)
