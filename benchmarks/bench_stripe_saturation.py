"""Centres of saturated (clipped) stripes with the default settings: bias and RMS per condition.

Renders of lightplane.simulate.saturated_stripe (straight Gaussian stripe, FWHM
5 px, tilt 0.06 rad, blur 0.7 px, noise 1 % of the clip level), peak 1x-8x the clip
level, uniform or as a hot spot (0.7x elsewhere), 8-bit / 16-bit / 12-bit in a
16-bit container; plus a symmetric halo, an asymmetric halo, a reflection 12 px
away and a laser-minus-background frame.  Errors: centre row minus the true
crossing of the centre line with the point's column (px).  Bars (issue):
|bias| <= 0.05 px, RMS <= 0.1 px.

Run: ``.venv/bin/python benchmarks/bench_stripe_saturation.py``.
"""

from __future__ import annotations

import numpy as np

from lightplane.simulate.saturated_stripe import SaturatedStripe, hot_spot, render_saturated
from lightplane.stripe.extract import extract_profile, extract_stripe
from results import at_least, at_most, figure, record, within


def errors(img, truth):
    out = {}
    prof = extract_profile(img)
    uv = prof.points
    out["extract_profile"] = (uv[:, 1] - truth(uv[:, 0]), prof.valid.mean())
    uv = extract_stripe(img).uv
    uv = uv[(uv[:, 0] > 10) & (uv[:, 0] < img.shape[1] - 10) & (np.abs(uv[:, 1] - truth(uv[:, 0])) < 6.0)]
    out["extract_stripe"] = (uv[:, 1] - truth(uv[:, 0]), len(uv) / (img.shape[1] - 20))
    return out


def main() -> None:
    hdr = f"{'condition':<44} {'function':<16} {'found':>6} {'bias':>8} {'RMS':>7} {'max':>6}  verdict"
    print(hdr)
    print("-" * len(hdr))
    conds = []
    for name, dtype, clip in (("8-bit", np.uint8, 255.0), ("16-bit", np.uint16, 65535.0),
                              ("12-bit in 16", np.uint16, 4095.0)):
        for a in (1.0, 2.0, 4.0, 8.0):
            for kind in ("uniform", "hot spot"):
                amp = hot_spot(a) if kind == "hot spot" else a
                conds.append((f"{name} {a:g}x {kind}", dict(amplitude=amp, clip=clip, dtype=dtype,
                                                              rng=np.random.default_rng(int(a * 10)))))
    for a in (2.0, 8.0):
        for name, kw in (("halo 15% FWHM 25 symmetric", dict(halo=(0.15, 25.0, 0.0))),
                         ("halo 15% FWHM 25 offset 6 px", dict(halo=(0.15, 25.0, 6.0))),
                         ("reflection 40% at 12 px", dict(secondary=(0.4, 12.0))),
                         ("laser minus background (20%)", dict(subtract=True, background=0.2))):
            conds.append((f"8-bit {a:g}x hot spot, {name}", dict(amplitude=hot_spot(a), rng=np.random.default_rng(5),
                                                                **kw)))
    worst: dict[str, list] = {}  # function -> [largest |bias|, largest RMS, conditions passing]
    for label, kw in conds:
        img, truth = render_saturated(SaturatedStripe(**{k: v for k, v in kw.items() if k != "rng"}), rng=kw["rng"])
        for fn, (e, found) in errors(img, truth).items():
            rms = float(np.sqrt(np.mean(e**2)))
            ok = abs(e.mean()) <= 0.05 and rms <= 0.1
            w = worst.setdefault(fn, [0.0, 0.0, 0])
            w[0] = max(w[0], abs(float(e.mean())))
            w[1] = max(w[1], rms)
            w[2] += int(ok)
            print(f"{label:<44} {fn:<16} {found:>6.2f} {e.mean():>+8.4f} {rms:>7.4f} {np.abs(e).max():>6.3f}  "
                  f"{'PASS' if ok else 'FAIL'}")
    n = len(conds)
    figs = []
    for fn, (bias, rms, passing) in worst.items():
        figs += [figure(f"{fn}_saturated_worst_bias", f"{fn}, saturated stripes: largest |bias|", bias, "px",
                        statistic=f"largest over {n} conditions", target=within(0.05, "px")),
                 figure(f"{fn}_saturated_worst_rms", f"{fn}, saturated stripes: largest RMS", rms, "px",
                        statistic=f"largest over {n} conditions", target=at_most(0.1, "px")),
                 figure(f"{fn}_saturated_passing", f"{fn}, saturated stripes: conditions passing", passing,
                        "conditions", statistic=f"count of {n} conditions", target=at_least(n, "conditions"))]
    record("bench_stripe_saturation", figs)


if __name__ == "__main__":
    main()
