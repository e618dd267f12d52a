"""Train the vessel UNet (guidewire3d.vessels2d_learned) on the 40 real coronary angiograms.

Honest evaluation first: k-fold cross-validation (default 5 folds of 8 held-out images, folds
drawn by a seeded permutation), each fold trained from scratch on the other images and scored
(Dice of ``learned_vessel_mask`` vs the manual mask) on its held-out images only. The mean
held-out Dice is the number that predicts unseen images. Then a final model is trained on all
images with the same recipe and written to ``resources/vessel_unet.safetensors`` (safetensors,
no pickle; the metadata records the recipe and the CV Dice). Trainings are independent, seeded
tasks, run on ``--workers`` processes (one torch thread each), so the result does not depend on
the number of workers.

Usage (the command that produced the shipped weights, ~25 min wall on 2 shared cores)::

    nice .venv/bin/python scripts/train_vessels2d.py --workers 2

Options: ``--folds 0`` skips cross-validation; ``--no-final`` skips the final model;
``--out PATH`` writes the weights elsewhere; ``--save-dir DIR`` also writes every fold's model;
``--rescore DIR`` trains nothing and scores the models of DIR again (after a change of the
inference post-processing), then writes the final one with the new scores.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

REAL_DIR = Path("/work/shared/data/coronary-angiograms")
RECIPE = dict(channels=(8, 16, 32, 64), steps=650, batch=8, crop_px=128, lr=3e-3)


def load_real(data_dir=REAL_DIR):
    """(ids, images, masks) of the real angiograms (``N.png`` with ``N_gt.png``)."""
    from skimage.io import imread

    data_dir = Path(data_dir)
    ids = sorted(int(p.stem) for p in data_dir.glob("*.png") if p.stem.isdigit())
    images = [imread(data_dir / f"{i}.png") for i in ids]
    masks = [imread(data_dir / f"{i}_gt.png") > 0 for i in ids]
    return ids, images, masks


def folds_of(n: int, k: int, seed: int) -> list[np.ndarray]:
    """k disjoint held-out index sets covering range(n) (seeded permutation)."""
    perm = np.random.default_rng(seed).permutation(n)
    return [np.sort(perm[f::k]) for f in range(k)]


def _task(args):
    """One training: ``(name, train_idx, test_idx, data_dir, seed, steps, save_dir)`` -> dict with the
    model state (scoring happens in the main process, see :func:`_score`)."""
    import torch

    torch.set_num_threads(1)
    from guidewire3d.vessels2d_learned import TrainOptions, VesselUNetConfig, save_vessel_unet, train_vessel_unet

    name, train_idx, test_idx, data_dir, seed, steps, save_dir = args
    ids, images, masks = load_real(data_dir)
    opts = TrainOptions(steps=steps, batch=RECIPE["batch"], crop_px=RECIPE["crop_px"], lr=RECIPE["lr"], seed=seed)
    t0 = time.perf_counter()
    model = train_vessel_unet([images[i] for i in train_idx], [masks[i] for i in train_idx],
                              config=VesselUNetConfig(channels=RECIPE["channels"]), options=opts,
                              log=lambda s, loss: print(f"  [{name}] step {s} loss {loss:.4f}", flush=True))
    train_s = time.perf_counter() - t0
    held = [ids[i] for i in test_idx]
    if save_dir:
        save_vessel_unet(model, Path(save_dir) / f"vessel_unet_{name}.safetensors",
                         extra_metadata={"held_out_ids": held, "recipe": json.dumps(asdict(opts))})
    state = {k: v.detach().clone() for k, v in model.state_dict().items()}
    return dict(name=name, train_s=train_s, held_out_ids=held, options=asdict(opts), state=state)


def _load_results(folder: Path) -> list[dict]:
    """Task results from the models a previous run wrote with ``--save-dir``."""
    from guidewire3d.vessels2d_learned import load_vessel_unet

    out = []
    for f in sorted(folder.glob("vessel_unet_*.safetensors")):
        m = load_vessel_unet(f)
        name = f.stem.removeprefix("vessel_unet_")
        if "recipe" in m.metadata:
            opts = json.loads(m.metadata["recipe"])
        else:  # files of a run before the recipe was recorded: the defaults and the task's seed
            seed = 0 if name == "final" else 1 + int(name.removeprefix("fold"))
            opts = dict(steps=RECIPE["steps"], batch=RECIPE["batch"], crop_px=RECIPE["crop_px"], lr=RECIPE["lr"],
                        seed=seed)
        out.append(dict(name=name, train_s=float("nan"), held_out_ids=json.loads(m.metadata["held_out_ids"]),
                        options=opts, state=m.state_dict()))
    return out


def _model(state):
    from guidewire3d.vessels2d_learned import VesselUNetConfig, build_vessel_unet

    model = build_vessel_unet(VesselUNetConfig(channels=RECIPE["channels"]))
    model.load_state_dict(state)
    model.eval()
    return model


def _score(model, ids, images, masks, which) -> dict[int, float]:
    """Dice of ``learned_vessel_mask`` (automatic polarity, as ``vessel_mask`` runs it) per image id."""
    from guidewire3d.metrics import dice
    from guidewire3d.vessels2d_learned import learned_vessel_mask

    pos = {i: k for k, i in enumerate(ids)}
    return {i: float(dice(learned_vessel_mask(images[pos[i]], model=model), masks[pos[i]])) for i in which}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(REAL_DIR))
    ap.add_argument("--folds", type=int, default=5, help="cross-validation folds (0: none)")
    ap.add_argument("--no-final", action="store_true", help="skip the final model on all images")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--steps", type=int, default=RECIPE["steps"], help="optimiser steps per training")
    ap.add_argument("--save-dir", default=None, help="also write every fold's model here")
    ap.add_argument("--rescore", default=None,
                    help="no training: score the models a previous run wrote to this --save-dir")
    ap.add_argument("--out", default=None, help="weights path (default resources/vessel_unet.safetensors)")
    args = ap.parse_args(argv)

    from guidewire3d.vessels2d_learned import DEFAULT_WEIGHTS_PATH, save_vessel_unet

    ids, images, masks = load_real(args.data)
    n = len(ids)
    if args.rescore:
        results = _load_results(Path(args.rescore))
        print(f"re-scoring {len(results)} models from {args.rescore}")
    else:
        tasks = []
        folds = folds_of(n, args.folds, args.seed) if args.folds > 1 else []
        for f, test in enumerate(folds):
            train = np.setdiff1d(np.arange(n), test)
            tasks.append((f"fold{f}", train.tolist(), test.tolist(), args.data, args.seed + 1 + f, args.steps,
                          args.save_dir))
        if not args.no_final:
            tasks.append(("final", list(range(n)), list(range(n)), args.data, args.seed, args.steps, args.save_dir))
        t0 = time.perf_counter()
        if args.workers > 1:
            with mp.get_context("spawn").Pool(args.workers) as pool:
                results = pool.map(_task, tasks, chunksize=1)
        else:
            results = [_task(t) for t in tasks]
        print(f"\ntotal wall {time.perf_counter() - t0:.0f} s; recipe {RECIPE}, steps {args.steps}")

    cv = [r for r in results if r["name"].startswith("fold")]
    summary = {}
    if cv:
        print("\n| fold | held-out images | Dice mean | Dice min | train s |")
        print("|---|---|---|---|---|")
        all_scores = {}
        fold_means = []
        for r in cv:
            sc = _score(_model(r["state"]), ids, images, masks, r["held_out_ids"])
            all_scores.update(sc)
            d = np.array(list(sc.values()))
            fold_means.append(d.mean())
            print(f"| {r['name'][4:]} | {' '.join(str(i) for i in sc)} | {d.mean():.3f} | {d.min():.3f} "
                  f"| {r['train_s']:.0f} |")
        fold_means = np.array(fold_means)
        per_image = np.array(list(all_scores.values()))
        print(f"\n{len(cv)}-fold CV held-out Dice: mean of fold means {fold_means.mean():.3f} "
              f"(std {fold_means.std(ddof=1):.3f}); over the {len(per_image)} held-out images mean "
              f"{per_image.mean():.3f}, median {np.median(per_image):.3f}, min {per_image.min():.3f}")
        summary = dict(cv_folds=len(cv), cv_dice_mean=round(float(per_image.mean()), 4),
                       cv_dice_median=round(float(np.median(per_image)), 4),
                       cv_fold_means=[round(float(x), 4) for x in fold_means],
                       cv_per_image={str(k): round(v, 4) for k, v in sorted(all_scores.items())})
    final = [r for r in results if r["name"] == "final"]
    if final:
        r = final[0]
        model = _model(r["state"])
        d = np.array(list(_score(model, ids, images, masks, ids).values()))
        print(f"\nfinal model (trained on all {n}): TRAINING-SET Dice mean {d.mean():.3f}, "
              f"median {np.median(d):.3f} (not a generalisation estimate; see the CV above)")
        meta = dict(training_data="coronary-angiograms (40 real non-subtracted, 300x300, manual masks)",
                    recipe=json.dumps({**r["options"], "channels": list(RECIPE["channels"])}),
                    train_dice_mean=f"{d.mean():.4f}", trainer="scripts/train_vessels2d.py",
                    **{k: (v if isinstance(v, str) else json.dumps(v)) for k, v in summary.items()})
        out = save_vessel_unet(model, args.out or DEFAULT_WEIGHTS_PATH, extra_metadata=meta)
        print(f"weights -> {out} ({out.stat().st_size / 1e6:.2f} MB)")


if __name__ == "__main__":
    main()
