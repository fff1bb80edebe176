#!/usr/bin/env python3
"""How far can a predicted TRE get on these data? An analysis of `librplus calibrate-error`'s
samples (FILE.samples.csv: one registration a row, features and true TRE), independent of the
product's fit: other model families on the same features, and oracles that know what surgery
cannot (each deformation's true mean TRE per category).

Not run by CI (needs numpy and scikit-learn):

    python3 -m venv /tmp/ana && /tmp/ana/bin/pip install numpy scikit-learn
    /tmp/ana/bin/python tests/reference/error_estimate_limits.py MODEL.json.samples.csv

Prints, per method, the held-out MAE and Pearson r of: the product's law (ridge, log-linear),
gradient boosting, the law with per-category interactions, oracles, the share of the error that
comes from failed registrations (TRE > 20 mm), and how well a logistic regression finds them.
RESULTS.md ("Error estimate") quotes its output.
"""

import csv
import sys

import numpy as np
from sklearn.ensemble import HistGradientBoostingRegressor
from sklearn.linear_model import LogisticRegression, Ridge
from sklearn.metrics import roc_auc_score

FAILED_MM = 20.0


def regressors(r):
    """The product's ErrorFeatures::regressors, from a CSV row."""
    g = lambda k: float(r[k])  # noqa: E731
    s = g("size_mm")
    return [
        np.log1p(g("surface_points")),
        np.log1p(g("ultrasound_points")),
        np.log(0.1 + g("residual_rms_mm")),
        np.log(0.1 + g("rigid_rms_mm")),
        np.log1p(max(g("strain_energy_uj"), 0.0)),
        np.log(0.1 + g("mean_displacement_mm")),
        g("coverage_mean_mm") / s,
        g("surface_covered"),
        np.log(s),
        np.log(0.1 + g("far_displacement_mm")),
        np.log(0.1 + g("max_displacement_mm")),
        g("coverage_p90_mm") / s,
    ]


def deformation(r):
    return r["scenario"].split("/")[0]


def main(path):
    rows = list(csv.DictReader(open(path)))
    for method in sorted({r["method"] for r in rows}):
        cal = [r for r in rows if r["method"] == method and r["set"] == "calibration"]
        held = [r for r in rows if r["method"] == method and r["set"] == "held_out"]
        if not cal or not held:
            continue
        x = np.array([regressors(r) for r in cal])
        xt = np.array([regressors(r) for r in held])
        y = np.array([float(r["true_tre_mm"]) for r in cal])
        yt = np.array([float(r["true_tre_mm"]) for r in held])
        mu, sd = x.mean(0), x.std(0) + 1e-12
        z, zt = (x - mu) / sd, (xt - mu) / sd

        def report(name, p):
            e = np.abs(p - yt)
            print(
                f"{method:9s} {name:44s} MAE {e.mean():5.2f}  median AE {np.median(e):5.2f}"
                f"  r {np.corrcoef(p, yt)[0, 1]:5.2f}"
            )

        law = Ridge(alpha=1.0).fit(z, np.log(y))
        smear = np.mean(np.exp(np.log(y) - law.predict(z)))
        one_law = np.exp(law.predict(zt)) * smear
        report("one log-linear law (version 1)", one_law)
        gbm = HistGradientBoostingRegressor(
            learning_rate=0.05, max_iter=300, max_leaf_nodes=15, min_samples_leaf=40,
            random_state=0,
        ).fit(x, y)
        report("gradient boosting on the same features", gbm.predict(xt))
        cats = sorted({r["category"] for r in rows})

        def inter(zm, rr):
            c = np.array([[r["category"] == k for k in cats] for r in rr], float)
            return np.hstack([zm] + [zm * c[:, [j]] for j in range(len(cats))] + [c])

        li = Ridge(alpha=3.0).fit(inter(z, cal), np.log(y))
        si = np.mean(np.exp(np.log(y) - li.predict(inter(z, cal))))
        report("log-linear law x category", np.exp(li.predict(inter(zt, held))) * si)
        failed = y > FAILED_MM
        if failed.sum() >= 10 and (yt > FAILED_MM).any():
            lr = LogisticRegression(C=1.0, max_iter=5000).fit(z, failed)
            p = lr.predict_proba(zt)[:, 1]
            ok_law = Ridge(alpha=1.0).fit(z[~failed], np.log(y[~failed]))
            so = np.mean(np.exp(np.log(y[~failed]) - ok_law.predict(z[~failed])))
            f_law = Ridge(alpha=1.0).fit(z[failed], np.log(y[failed]))
            sf = np.mean(np.exp(np.log(y[failed]) - f_law.predict(z[failed])))
            mix = p * np.exp(f_law.predict(zt)) * sf + (1 - p) * np.exp(ok_law.predict(zt)) * so
            report("failure part (version 2)", mix)
            print(
                f"{method:9s}   failed (TRE > {FAILED_MM:.0f} mm) held out: {(yt > FAILED_MM).sum()}"
                f" of {len(yt)}, AUC of the logistic probability"
                f" {roc_auc_score(yt > FAILED_MM, p):.3f}; their share of the version-1 absolute"
                f" error {np.abs(one_law - yt)[yt > FAILED_MM].sum() / np.abs(one_law - yt).sum():.2f};"
                f" version-1 MAE without them {np.abs(one_law - yt)[yt <= FAILED_MM].mean():.2f}"
            )
        for name, key in [
            ("oracle: each deformation's true mean", deformation),
            ("oracle: each deformation x category's mean", lambda r: (deformation(r), r["category"])),
        ]:
            cell = {}
            for r in held:
                cell.setdefault(key(r), []).append(float(r["true_tre_mm"]))
            report(name, np.array([np.mean(cell[key(r)]) for r in held]))


if __name__ == "__main__":
    main(sys.argv[1])
