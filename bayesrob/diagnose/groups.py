"""Diagnosis of any robot (URDF/DH chains and trees, the planar arms as 2-joint chains): which
physical effects does the geometric calibration miss (``frames,geometric``, with ``servo``
where the commands pass through a servo map: :func:`~bayesrob.calibrate.least_squares.base_groups`)?

Each candidate effect is a calibration group (``joint_compliance``: ``compliance``;
``lateral_compliance``: ``lateral``; ``encoder_error``: ``encoder``; ``servo_nonlinearity``:
``servo_curve``, where a servo map is; ``backlash``, tried once compliance is named, since only
a fitted deflection says which side a joint rests on, or with it where nothing passes alone).
Effects are named greedily: each round fits every remaining candidate on most ``train`` poses
and scores it on the *selection* poses (drawn with the seed; a rig with few train poses is
scored over several disjoint folds, each fitted without its own, until MIN_SCORED_POSES poses
are). The decision is the one rule of every robot (:class:`~bayesrob.diagnose.rule.DecisionRule`,
the planar refits' too): a candidate passes when its paired per-row error drop there exceeds
``rule.Z`` standard errors; the one dropping the mean error most per added parameter is named
(so compliance goes before an encoder sinusoid that mimics part of it). A passing candidate
within ``rule.Z`` standard errors of the named one is reported as its *rival*. The
``validation`` rows are never looked at while deciding: the ladder (errors after each named
effect, refitted on every train row) is reported on them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.stats

from bayesrob.calibrate.least_squares import (
    SAG_CONVERGED_MM,
    Calibration,
    base_groups,
    calibrate,
    marker_residuals,
    sag_convergence,
)
from bayesrob.data.rig import Rig
from bayesrob.data.vocabulary import CHAIN_EFFECTS
from bayesrob.diagnose.rule import DecisionRule, Z, elpd_diff, paired_z, public_scores
from bayesrob.robot import SAG_GROUPS
from bayesrob.robot.effects import ALIASES, ENCODER_EFFECTS, SERVO_EFFECTS, resolve_effects

# effect -> the effect it builds on, named first. Backlash without a fitted compliance has no
# side; fitted with it in one candidate it only cost time (seed 11: less drop per parameter
# than joint compliance alone; with stiff joints z 1.6).
NEEDS = {"backlash": "joint_compliance"}
# Once an effect is named, backlash and encoder fits start from the named model's fit with
# fewer evaluations (from the nominal robot each took 23-32 s on Justin); the compliance
# groups start from the nominal robot (from the named fit, lateral compliance stopped at 4.05
# mm on Justin's selection poses against 3.48).
WARM_STARTED = ("encoder_error", "backlash")
WARM_NFEV = 40
SELECTION_SHARE = 0.25  # of the train poses, held back to decide on
# Poses a decision is scored on at the least: the 20 a 6-joint arm's 80 train poses give at
# SELECTION_SHARE, where the rule was chosen (tuning seeds 61-62). A rig with fewer train poses
# (a planar arm's 16) is scored over several disjoint folds, each fitted without its poses.
MIN_SCORED_POSES = 20
# Least-squares evaluations per stage of a selection fit: on Justin 140 (of 320) left every
# selection error as before to 0.01 mm (drops between candidates: 0.1-5 mm), in half the time.
SELECTION_NFEV = 140
# The parameter guard is reported beside each candidate and step and decides for a pair tried
# because nothing passed alone: unguarded, a 17-parameter pair passed on the clean arm6 of
# tuning seed 11 (4.9 nats) and made its validation worse.
RULE = DecisionRule()


class DiagnosisError(ValueError):
    """A rig cannot be diagnosed as asked; the message is one line."""


@dataclass
class GroupDiagnosis:
    rig: str
    effects: list[str]
    rounds: list[list[dict]]
    steps: list[dict]
    baseline: dict
    seconds: float
    selection_rows: int
    notes: list[str] = field(default_factory=list)
    sag_steps: int = 1  # torque steps asked of the ladder's fits with gravity
    selection_folds: int = 1  # disjoint sets of selection poses, each fitted without its own
    # step label -> {arm: (observed markers, residuals)} on the validation rows, for the
    # geometric calibration and the final model (figures only; not in the JSON)
    residuals: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]] = field(
        default_factory=dict, repr=False)

    def to_json(self) -> dict:
        """``bayesrob diagnose RIG --json``'s document on a chain rig."""
        last = self.steps[-1] if self.steps else self.baseline
        return {
            "rig": self.rig, "robot": "chain", "effects": self.effects,
            "rule_z": Z,
            "rule": (f"of the candidates whose paired error drop on the selection poses "
                     f"({self.selection_rows} train rows held back over "
                     f"{self.selection_folds} fold(s), each fitted without its own) exceeds "
                     f"{Z:g} standard errors, name the one with the largest drop per added "
                     "parameter (backlash is tried once joint_compliance is named, or where "
                     "nothing passes alone with it, both named where the pair also beats "
                     "joint_compliance alone and clears the parameter guard; a candidate left "
                     "no identifiable parameter never passes); validation rows only report"),
            "steps": self.steps, "rounds": self.rounds,
            "baseline": self.baseline,
            "baseline_heldout_error_mm": self.baseline["heldout_error_mm"],
            "final_heldout_error_mm": last["heldout_error_mm"],
            "seconds": self.seconds, "notes": self.notes, "sag_steps": self.sag_steps,
            "selection_folds": self.selection_folds,
        }

    to_dict = to_json


def _folds(rig: Rig, seed: int) -> list[Rig]:
    """The rig with a share of its train poses relabelled ``selection``, once per fold: the
    first fold as drawn with the seed, then disjoint others until at least MIN_SCORED_POSES
    poses are scored (at most every train pose once)."""
    meas = rig.measurements
    train = np.flatnonzero(meas.set == "train")
    pose = meas.extra.get("pose")
    keys = np.array([pose[i] for i in train]) if pose else train.astype(str)
    poses = np.unique(keys)
    rng = np.random.default_rng(seed)
    size = max(1, round(SELECTION_SHARE * len(poses)))
    first = rng.choice(poses, size=size, replace=False)
    rest = rng.permutation(np.setdiff1d(poses, first))
    n_folds = min(max(1, -(-MIN_SCORED_POSES // size)), 1 + len(rest) // size)
    out = []
    for chosen in [first, *(rest[k * size:(k + 1) * size] for k in range(n_folds - 1))]:
        sets = meas.set.copy()
        sets[train[np.isin(keys, chosen)]] = "selection"
        out.append(replace(rig, measurements=replace(meas, set=sets)))
    return out


def _selection_rows(rig: Rig, cal: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """Per selection row: the marker error (mm) and its log predictive density, Gaussian in
    each axis with the variance the fit leaves on its train rows (degrees of freedom counted)."""
    train = marker_residuals(rig, cal.robot, cal.x, "train")
    r = np.concatenate([train[a][1] for a in sorted(train)])
    var = float(np.sum(r * r)) / max(r.size - int(cal.ident.free.sum()), 1)
    sel = marker_residuals(rig, cal.robot, cal.x, "selection")
    r = np.concatenate([sel[a][1] for a in sorted(sel)])
    return (np.linalg.norm(r, axis=1),
            scipy.stats.norm.logpdf(r, scale=np.sqrt(var)).sum(axis=1))


def _fold_fits(folds: list[Rig], groups: tuple[str, ...], starts: list[np.ndarray] | None,
               nfev: int, bar) -> tuple[tuple[np.ndarray, np.ndarray], list[np.ndarray],
                                        Calibration]:
    """Each fold fitted without its selection poses (from ``starts`` where given) and scored
    on them: the per-row errors and log densities of every fold, end to end; each fold's
    parameters; the first fold's calibration (its rank analysis counts the parameters)."""
    rows, xs, first = [], [], None
    for k, fold in enumerate(folds):
        cal = calibrate(fold, groups, polish=False, max_nfev=nfev,
                        **({"start": starts[k]} if starts is not None else {}))
        rows.append(_selection_rows(fold, cal))
        xs.append(cal.x)
        if first is None:
            first = cal
        bar.update(1)
    return ((np.concatenate([r[0] for r in rows]), np.concatenate([r[1] for r in rows])),
            xs, first)


def _ladder_fit(rig: Rig, groups: tuple[str, ...], sag_steps: int, notes: list[str]
                ) -> Calibration:
    """A ladder step refitted on every train row, its gravity torques taken ``sag_steps``
    times; where that fit would be off its equilibrium (one more step moves a train marker over
    SAG_CONVERGED_MM) it is an iteration, not a physical model, so the step is reported at one
    step and a note says so. The one-step fit comes first: it is the fallback, and where its
    own sag does not settle in ``sag_steps`` steps the equilibrium fit is not tried (on
    Justin the joint-compliance step's six-step fit, 35-40 s, ended 16 mm off its
    equilibrium; the selection fit's sag, on a quarter fewer rows, had settled)."""
    one = calibrate(rig, groups)
    if sag_steps == 1 or not set(SAG_GROUPS) & set(groups):
        return one
    label = ",".join(groups)
    moved = sag_convergence(rig, one.x, sag_steps)["sag_next_step_mm"]
    if moved > SAG_CONVERGED_MM:
        notes.append(f"{label}: the one-step fit's sag does not settle in {sag_steps} steps "
                     f"of the torques (one more moves a train marker by {moved:.3g} mm): no "
                     "equilibrium fitted; reported with one step, the first-order model")
        return one
    cal = calibrate(rig, groups, sag_steps=sag_steps)
    moved = cal.extra["sag_next_step_mm"]
    if moved <= SAG_CONVERGED_MM:
        return cal
    notes.append(f"{label}: not at equilibrium after {sag_steps} steps of the torques "
                 f"(one more moves a train marker by {moved:.3g} mm): reported with one step, "
                 "the first-order model")
    return one


def diagnose_groups(rig: Rig, effects: Sequence[str] | None = None, *, seed: int = 0,
                    progress: bool = False, sag_steps: int = 1) -> GroupDiagnosis:
    """Name the effects the geometric calibration of a rig misses (module docstring);
    ``sag_steps`` applies to the ladder's fits only (:func:`_ladder_fit`), so the names do not
    depend on it."""
    import time

    from bayesrob.progress import progress as make_progress

    t0 = time.perf_counter()
    if sag_steps < 1:
        raise DiagnosisError(f"sag_steps must be at least 1, not {sag_steps}")
    try:
        candidates = resolve_effects(effects, chain=True, robot=rig.robot)
    except ValueError as e:
        raise DiagnosisError(str(e)) from None
    if not len(rig.rows(rig.robot.measured_arms()[0], "validation")[0]):
        raise DiagnosisError(f"{rig.path or rig.name}: no validation rows to report the "
                                  "ladder on")
    folds = _folds(rig, seed)
    n_sel = sum(int((f.measurements.set == "selection").sum()) for f in folds)
    base = groups = base_groups(rig.robot)
    named: list[str] = []
    rivals: list[list[str]] = []  # per named effect
    guarded: list[bool] = []  # per named effect: its step clears the parameter guard
    named_in: list[int] = []  # per named effect: the round (from 1) that named it
    rounds: list[list[dict]] = []
    # at most: every candidate in every round and each pair once (a pair that fails ends the
    # rounds), then the ladder (made exact once the rounds end)
    pairs = sum(1 for e in NEEDS if e in candidates)
    total = (len(folds) * (sum(range(1, len(candidates) + 1)) + 1 + pairs)
             + len(candidates) + 1)
    with make_progress(total, "diagnose", "fits", enabled=progress) as bar:
        before, _, cal = _fold_fits(folds, groups, None, SELECTION_NFEV, bar)
        n_before = int(cal.ident.free.sum())
        # each named effect's selection fits (one per fold): the last named model's are where
        # the WARM_STARTED candidates start
        selected: dict[str, list[np.ndarray]] = {}

        def score(effects: tuple[str, ...], starts: list[np.ndarray] | None) -> dict:
            """A candidate (an effect, or one with the effect it builds on) fitted on the
            folds and scored against the current model's selection errors."""
            added_groups = tuple(CHAIN_EFFECTS[e] for e in effects)
            after, xs, cal = _fold_fits(folds, (*groups, *added_groups), starts,
                                        WARM_NFEV if starts is not None else SELECTION_NFEV,
                                        bar)
            added = int(cal.ident.free.sum()) - n_before
            # its own group, not the net count: freeing the links' masses may change that
            # count by itself
            own = bool(cal.ident.free[cal.robot.layout.group_mask(added_groups[-1:])].any())
            gain, gain_se = elpd_diff(before[1], after[1])
            err0, err1 = float(before[0].mean()), float(after[0].mean())
            z = paired_z(before[0], after[0])
            s = {"effect": "+".join(effects), "parameters": added,
                 "selection_error_before_mm": err0,
                 "selection_error_after_mm": err1, "z": z,
                 "drop_per_parameter_mm": (err0 - err1) / max(added, 1),
                 # the selection rows' log density gain and the parameter guard's
                 # verdict on it: reported, not deciding (docs/diagnose.md, "The
                 # parameter guard")
                 "elpd_diff": gain, "elpd_diff_se": gain_se,
                 "guard_nats": RULE.threshold(added),
                 "_effects": effects, "_after": after, "_x": xs}
            s["guard_passes"] = RULE.guard_passes(s)
            # a candidate the rank analysis leaves nothing to fit (lateral bending under
            # gravity in a planar arm's plane) moves the errors by rounding alone: its z is
            # noise
            s["passes"] = bool(own and RULE.passes(s))
            return s

        while len(named) < len(candidates):
            scores = []
            for eff in (c for c in candidates
                        if c not in named and NEEDS.get(c, c) in (*named, c)):
                # compared with each other, not reported: the fast fit is enough to decide
                warm = eff in WARM_STARTED and bool(named)
                scores.append(score((eff,), selected[named[-1]] if warm else None))
            if not any(s["passes"] for s in scores):
                # nothing passes alone: an effect that builds on another not named (play,
                # which takes its side from a fitted deflection) is tried with it, and
                # passes where each is needed, beyond the current model and beyond the
                # other alone (the planar engine's pairs), and it clears the guard
                for eff, first in NEEDS.items():
                    alone = [s for s in scores if s["effect"] == first]
                    if eff not in candidates or eff in named or not alone:
                        continue
                    pair = score((first, eff), None)
                    pair["z_vs_alone"] = paired_z(alone[0]["_after"][0], pair["_after"][0])
                    pair["passes"] = bool(pair["passes"]
                                          and RULE.pair_passes(pair, [pair["z_vs_alone"]]))
                    scores.append(pair)
            passing = [s for s in scores if s["passes"]]
            best = None
            if passing:
                # of the candidates that pass, the one that explains the most per parameter
                # it adds: the largest drop of the mean selection error per added parameter
                best = RULE.best(passing)
                for s in passing:
                    if s is not best:
                        # positive where the named effect leaves the smaller errors
                        s["z_vs_named"] = paired_z(s["_after"][0], best["_after"][0])
            rounds.append(public_scores(scores))
            if best is None:
                break
            # a passing candidate the selection poses cannot tell from the named one: the
            # name is the rule's choice between fits the data hold equally good
            close = [s["effect"] for s in passing if abs(s.get("z_vs_named", np.inf)) <= Z]
            for eff in best["_effects"]:  # a pair names both, the one built on first
                rivals.append(close)
                guarded.append(best["guard_passes"])
                named_in.append(len(rounds))
                named.append(eff)
                selected[eff] = best["_x"]
                groups = (*groups, CHAIN_EFFECTS[eff])
            before, n_before = best["_after"], n_before + best["parameters"]
        # the selection is over: what is left is known, a ladder fit per step and the base
        planned = bar.total
        bar.total = bar.n + len(named) + 1
        if bar.total < planned:  # say why the count fell rather than let it jump
            bar.set_postfix(f"{planned - bar.total} planned fits not needed: the selection "
                            f"named {len(named)} of {len(candidates)} candidates")
        # the ladder: every step refitted on all train rows, reported on the validation rows
        steps, ladder = [], [base]
        for eff in named:
            ladder.append((*ladder[-1], CHAIN_EFFECTS[eff]))
        baseline: dict = {}
        residuals = {}
        ladder_notes: list[str] = []
        for k, g in enumerate(ladder):
            cal = _ladder_fit(rig, g, sag_steps, ladder_notes)
            bar.update(1)
            # the calibration already scored every set: its validation statistics are the
            # ladder's (validation rows exist, checked above)
            val = cal.errors["validation"]["all"]
            row = {"groups": list(g), "n_free": int(cal.ident.free.sum()),
                   "train_error_mm": cal.errors["train"]["all"]["mean_mm"],
                   "heldout_error_mm": val["mean_mm"], "heldout_error_sd_mm": val["sd_mm"],
                   "heldout_error_max_mm": val["max_mm"], "n": val["n"]}
            if "holdout" in cal.errors:
                row["holdout_error_mm"] = cal.errors["holdout"]["all"]["mean_mm"]
            if "sag_steps" in cal.extra:
                row["sag_steps"] = cal.extra["sag_steps"]
                row["sag_next_step_mm"] = cal.extra["sag_next_step_mm"]
            if k in (0, len(ladder) - 1):
                label = "geometric" if k == 0 else "+ " + " + ".join(named)
                residuals[label] = marker_residuals(rig, cal.robot, cal.x, "validation")
            if k == 0:
                baseline = row
            else:
                steps.append({"effect": named[k - 1], "rivals": rivals[k - 1],
                              "guard_passes": guarded[k - 1], "round": named_in[k - 1],
                              **row})
    # the servo or encoder effects resolve_effects left out of the default candidates
    notes = [f"{e} not tried: the robot's columns are its joint values (no servo map; "
             "encoder_error is their error)" for e in SERVO_EFFECTS
             if effects is None and e not in candidates]
    notes += [f"{e} not tried: the commands pass through a servo map, whose curve "
              "servo_nonlinearity fits (no joint encoder is read)" for e in ENCODER_EFFECTS
              if effects is None and e not in candidates]
    notes += [f"{c} not tried: it builds on {NEEDS[c]}, which was not named"
              for c in candidates if c in NEEDS and NEEDS[c] not in named]
    notes += ladder_notes
    return GroupDiagnosis(rig.name, named, rounds, steps, baseline,
                          time.perf_counter() - t0, n_sel, notes, sag_steps,
                          selection_folds=len(folds), residuals=residuals)


def parse_published(text: str) -> dict[str, float]:
    """``geometric=10.5,joint_compliance=5.64`` -> the ladder's labels and means (mm): a
    published ladder to draw beside ours. Effect names may carry their leading ``+``."""
    out: dict[str, float] = {}
    for item in (t.strip() for t in text.split(",") if t.strip()):
        label, sep, value = item.partition("=")
        label = label.strip().lstrip("+").strip()
        label = {p: c for c, p in ALIASES.items()}.get(label, label)
        if not sep or label not in ("geometric", *CHAIN_EFFECTS):
            raise DiagnosisError(
                f"--published: expected STEP=MM with STEP one of geometric, "
                f"{', '.join(CHAIN_EFFECTS)}; got {item!r}")
        try:
            mm = float(value)
        except ValueError:
            raise DiagnosisError(f"--published: {label}: expected a number of mm, got "
                                      f"{value.strip()!r}") from None
        if not mm >= 0:
            raise DiagnosisError(f"--published: {label}: a mean error is >= 0, got {mm}")
        out["geometric" if label == "geometric" else f"+{label}"] = mm
    return out
