"""Trained nets: build a net from its spec, read a checkpoint, and prepare an ONV the way the net was trained.

Every training run (:mod:`warp_vision.train`) saves, beside the weights, the net's *spec*: a dict of
plain values and tensors naming a builder and its arguments (for a liNet, the photoreceptor positions its
connectivity is drawn on). :func:`build_net` turns a spec into the untrained net, the same call the
training run made; :func:`load_net` builds it and loads a checkpoint's weights. So the simulation and any
other user load a trained net with this module alone, never with the training code.

Checkpoint keys read here: ``model`` (state dict), ``net`` (spec), ``norm`` (input/target normalisation),
``config`` (the run's config as a dict, without paths), ``data`` (the dataset's config as a dict), and
``integrity``: the sha256 of everything else (:func:`content_digest`), which :func:`read_checkpoint`
checks, so a damaged file is an error that names it, never a net with a flipped bit.
"""

from __future__ import annotations

import errno
import hashlib
import json
import pickle
import zipfile
from pathlib import Path

import numpy as np
import torch


def _array(x) -> np.ndarray | None:
    if x is None:
        return None
    return x.numpy() if torch.is_tensor(x) else np.asarray(x)


def _foveation(spec: dict):
    from warp_vision.nn.connectivity import onv_positions
    from warp_vision.nn.heads import foveation_net

    angles = _array(spec.get("photoreceptor_angles"))
    if spec["model"] == "conv":
        from warp_vision.nn.retina_conv import RetinaConv, RetinaConvFoveationNet

        torch.manual_seed(spec["seed"])
        backbone = RetinaConv(_array(spec["photoreceptor_xy"]), spec["layers"], spec["reduction"], spec["channels"],
                              spec["seed"])
        return RetinaConvFoveationNet(backbone, angles)
    if spec["model"] == "cnn":
        from warp_vision.nn.retina_cnn import CONSENSUS_VIEWS, RetinaCNNFoveationNet

        torch.manual_seed(spec["seed"])
        # a spec from before the consensus read-out reads with it too (inference only: the weights are the same)
        return RetinaCNNFoveationNet(angles, spec["image_size"], spec["channels"],
                                     views=spec.get("views", CONSENSUS_VIEWS))
    return foveation_net(spec["model"], onv_positions(_array(spec["photoreceptor_xy"])), spec["layers"],
                         spec["receptive_field"], spec["reduction"], spec["seed"], head=spec["head"],
                         input_angles=None if angles is None else np.repeat(angles, 3, axis=0))


def _afr(spec: dict):
    from warp_vision.nn.connectivity import onv_positions
    from warp_vision.nn.heads import afr_net

    return afr_net(onv_positions(_array(spec["photoreceptor_xy"])), spec["identities"], spec["layers"],
                   spec["receptive_field"], spec["reduction"], spec["seed"], spec["model"])


def _oculomotor(spec: dict):
    from warp_vision.nn.heads import OculomotorNet

    torch.manual_seed(spec["seed"])
    return OculomotorNet(hidden=spec["hidden"])


def _pupil(spec: dict):
    from warp_vision.nn.intraocular import PupilNet

    torch.manual_seed(spec["seed"])
    return PupilNet(_array(spec["photoreceptor_xy"]), spec["hidden"], spec["rings"], spec["sectors"])


def _lens(spec: dict):
    from warp_vision.nn.intraocular import LensNet

    torch.manual_seed(spec["seed"])
    return LensNet(_array(spec["photoreceptor_xy"]), _array(spec["central"]), spec["photoreceptors"], spec["hidden"],
                   spec["samples_per_receptor"])


def _arm(spec: dict):
    from warp_vision.nn.arm import ArmNets

    torch.manual_seed(spec["seed"])
    return ArmNets(hidden=spec["hidden"])


def _limb(spec: dict):
    if spec["model"] == "cnn":
        from warp_vision.nn.retina_cnn import RetinaCNNLimbNet

        torch.manual_seed(spec["seed"])
        return RetinaCNNLimbNet(_array(spec["photoreceptor_angles"]), spec["image_size"], spec["channels"])
    if spec["model"] == "range":
        from warp_vision.nn.retina_cnn import RetinaCNNRangeNet

        torch.manual_seed(spec["seed"])
        return RetinaCNNRangeNet(_array(spec["photoreceptor_angles"]), spec["image_size"], spec["channels"],
                                 spec["max_ecc_deg"], spec["power"])
    from warp_vision.nn.connectivity import onv_positions
    from warp_vision.nn.heads import limb_vision_net

    return limb_vision_net(spec["model"], onv_positions(_array(spec["photoreceptor_xy"])), spec["layers"],
                           spec["receptive_field"], spec["reduction"], spec["seed"])


def _verify(spec: dict):
    from warp_vision.nn.verify import verify_net

    return verify_net(spec)


#: spec["kind"] -> the function that builds the untrained net from the spec
BUILDERS = {"foveation": _foveation, "afr": _afr, "oculomotor": _oculomotor, "pupil": _pupil, "lens": _lens,
            "arm": _arm, "limb": _limb, "verify": _verify}

#: the ONV dtypes a net can read (spec["onv_dtype"]; checkpoints without one read float32)
ONV_DTYPES = {"float32": torch.float32, "float16": torch.float16, "bfloat16": torch.bfloat16}


def onv_dtype(spec: dict) -> torch.dtype:
    """The dtype a net built from ``spec`` reads its ONVs in (:func:`net_input`)."""
    return ONV_DTYPES[spec.get("onv_dtype", "float32")]


def _first_layer(model: torch.nn.Module):
    """The first layer of a net's liNet backbone (None for a net without one)."""
    return getattr(getattr(model, "backbone", None), "layers", [None])[0]


def _read_half_onvs(model: torch.nn.Module, spec: dict) -> torch.nn.Module:
    """A liNet net whose spec reads half-precision ONVs standardises them in its first layer."""
    if onv_dtype(spec) != torch.float32:
        first = _first_layer(model)
        if not hasattr(first, "fold_input_standardisation"):
            raise ValueError(f"onv_dtype: {spec['onv_dtype']} ONVs need a liNet backbone; use float32 for "
                             f"{spec.get('model')!r}")
        first.fold_input_standardisation()
    return model


def set_input_standardisation(model: torch.nn.Module, norm: dict) -> None:
    """Give a net that standardises its input in its first layer (half-precision ONVs) the mean and std
    of :func:`fit_input_norm`; nets that read standardised float32 ONVs are left as they are."""
    first = _first_layer(model)
    if getattr(first, "folds_input", False):
        with torch.no_grad():
            first.input_mean.copy_(torch.as_tensor(norm["input_mean"]))
            first.input_std.copy_(torch.as_tensor(norm["input_std"]))


def build_net(spec: dict, device: str = "cpu") -> torch.nn.Module:
    """The untrained net a spec describes, on ``device`` (initialised from the spec's seed)."""
    kind = spec.get("kind") if isinstance(spec, dict) else None
    if kind not in BUILDERS:
        raise ValueError(f"net spec: expected a dict with kind one of {sorted(BUILDERS)}, got {kind!r}")
    return _read_half_onvs(BUILDERS[kind](spec), spec).to(device)


INTEGRITY_VERSION = 1


def _feed(h, x) -> None:
    """Feed ``x`` (nested dicts, lists, tensors, numbers, strings, None) to hash ``h``, unambiguously."""
    if torch.is_tensor(x):
        t = x.detach().cpu().contiguous()
        h.update(f"T{t.dtype}{tuple(t.shape)}:".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    elif isinstance(x, dict):
        h.update(f"D{len(x)}:".encode())
        for k in sorted(x, key=str):
            _feed(h, k)
            _feed(h, x[k])
    elif isinstance(x, (list, tuple)):
        h.update(f"L{len(x)}:".encode())
        for v in x:
            _feed(h, v)
    else:
        h.update(f"{type(x).__name__}:{x!r};".encode())


def content_digest(ck: dict) -> str:
    """sha256 over a checkpoint's contents (every key but ``integrity``): tensors by dtype, shape and bytes."""
    h = hashlib.sha256()
    _feed(h, {k: v for k, v in ck.items() if k != "integrity"})
    return h.hexdigest()


def seal(ck: dict) -> dict:
    """``ck`` with its ``integrity`` entry: the digest :func:`read_checkpoint` verifies."""
    return {**ck, "integrity": {"version": INTEGRITY_VERSION, "sha256": content_digest(ck)}}


def read_checkpoint(path, map_location="cpu") -> dict:
    """A checkpoint's verified contents (``torch.load(..., weights_only=True)``). A missing file raises
    FileNotFoundError; an unreadable one, one without a checksum, or one whose contents do not match its
    checksum raise ValueError, in one line that names the file."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such checkpoint")
    # (torch's own words for a text file advised weights_only=False)
    if path.is_file() and not zipfile.is_zipfile(path):
        raise ValueError(f"{path}: not a readable checkpoint: not a whole zip archive as torch.save writes "
                         f"(truncated, or another kind of file)")
    try:
        ck = torch.load(path, weights_only=True, map_location=map_location)
    except pickle.UnpicklingError:  # a zip archive whose pickle holds more than tensors and plain values
        raise ValueError(f"{path}: not a checkpoint of this package: it holds objects that a weights-only load "
                         f"refuses (torch.save of other code)") from None
    except Exception as e:  # a damaged archive: torch raises many kinds
        what = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ValueError(f"{path}: not a readable checkpoint ({what})") from None
    seal_ = ck.get("integrity") if isinstance(ck, dict) else None
    if not isinstance(seal_, dict) or "sha256" not in seal_:
        raise ValueError(f"{path}: the checkpoint carries no checksum (not written by this version); retrain it")
    if content_digest(ck) != seal_["sha256"]:
        raise ValueError(f"{path}: checksum mismatch: the file is damaged (its contents differ from when it was "
                         "written)")
    return ck


#: A run's settings that say where it reads and writes, or how long it may train, not what it is: left out of
#: its id (:func:`run_identity`), so a resumed run under a new epoch cap, or a run directory moved, is the same run.
NOT_IDENTITY = ("out", "data_dir", "identities_cache", "epochs", "device")
#: the settings that name which eye (or arm) a run's net serves
SIDE_FIELDS = ("eye", "side")


def _digest(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


def run_identity(task: str, config: dict) -> dict:
    """What a run is, from its task and its settings (config.json, or a checkpoint's config): {"task", "run": the
    run's id, a digest of every setting but :data:`NOT_IDENTITY`, and "eye" or "side" where the task has one}.
    Two runs of one id train the same net on the same data."""
    settings = {k: v for k, v in config.items() if k not in NOT_IDENTITY and k != "task"}
    ident = {"task": task, "run": _digest([task, settings])}
    ident.update({k: config[k] for k in SIDE_FIELDS if k in config})
    return ident


def new_binding(task: str, config: dict, data_config: dict, dataset: str | None) -> dict:
    """The ``binding`` a checkpoint carries: :func:`run_identity`, the digest of its dataset's config
    (``data_config``) and ``dataset``, the dataset's id (its content digest:
    :meth:`warp_vision.data.store.ChunkedStore.content_digest`; None for a task without a store)."""
    return {**run_identity(task, config), "data_config": _digest(data_config), "dataset": dataset}


def binding(ck: dict) -> dict:
    """What checkpoint ``ck`` belongs to: its ``binding``; for a checkpoint written before bindings, the
    identity its task and config give (without the dataset's id)."""
    b = ck.get("binding")
    if isinstance(b, dict) and "run" in b:
        return b
    config = ck.get("config") if isinstance(ck.get("config"), dict) else {}
    return run_identity(str(ck.get("task", "foveation")), config)


def describe_binding(b: dict) -> str:
    """"the left eye's foveation run 3f2a9c1b04d7e655", "the right arm's arm run ...", "a foveation net"."""
    side = next((f"{b[k]} {'arm' if k == 'side' else 'eye'}'s " for k in SIDE_FIELDS if b.get(k)), "")
    what = f"{b.get('task', 'unknown')} {'run ' + b['run'] if b.get('run') else 'net'}"
    return f"the {side}{what}" if side or b.get("run") else f"a {what}"


def require_binding(ck: dict, expect: dict, source, owner: str | None = None, settings: dict | None = None) -> None:
    """Refuse checkpoint ``ck`` (read from ``source``) where its :func:`binding` differs from ``expect`` (any of
    "task", "run", "eye", "side"; a None value is not checked): one ValueError naming what the checkpoint
    belongs to and what it was expected to belong to: ``owner`` ("the run in runs/x", followed by what that run
    is), or ``expect`` in words. With ``settings`` (the owner's config), the settings that differ are named."""
    got = binding(ck)
    differ = [k for k, v in expect.items() if v is not None and got.get(k) != v]
    if not differ:
        return
    why = ""
    theirs = ck.get("config") if isinstance(ck.get("config"), dict) else None
    if settings is not None and theirs is not None:
        keys = [k for k in sorted(set(settings) | set(theirs)) if k not in NOT_IDENTITY and k != "task"
                and json.dumps(settings.get(k), default=str) != json.dumps(theirs.get(k), default=str)]
        why = "".join(f"; {k} {theirs.get(k)!r} there, {settings.get(k)!r} here" for k in keys[:4])
    wanted = describe_binding({k: v for k, v in expect.items() if v is not None})
    owner = wanted if owner is None else f"{owner} ({wanted})"
    raise ValueError(f"{source} belongs to {describe_binding(got)}, not to {owner}{why}")


def dataset_mismatch(ck: dict, digest: str | None) -> bool:
    """Whether the dataset whose content digest is ``digest`` holds other samples than checkpoint ``ck`` was
    trained on (False where either is unknown: a checkpoint written before bindings, a task without a store)."""
    trained = binding(ck).get("dataset")
    return bool(trained and digest and trained != digest)


#: a run's checkpoints: its best validation epoch's weights (best.pt) and its last epoch's (latest.pt)
CHECKPOINTS = ("best", "latest")
#: the lock file a training process holds in its run directory while it trains
#: (:class:`warp_vision.fileio.FileLock`; taken by ``train.rundir.hold_run_dir``, waited on by the simulation)
TRAINING_LOCK = ".training.lock"


def read_run_config(run_dir) -> dict | None:
    """``run_dir/config.json`` as a dict, or None where there is none. A file that is not a JSON object (cut
    short, edited by hand) is a ValueError naming it, not a bare JSON error or a traceback."""
    path = Path(run_dir) / "config.json"
    if not path.is_file():
        return None
    try:
        cfg = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: not a run's config, it does not read as JSON ({e})") from None
    if not isinstance(cfg, dict):
        raise ValueError(f"{path}: not a run's config: a JSON {type(cfg).__name__}, where a run writes an object of "
                         "settings")
    return cfg


def saved_task(run_dir, config: dict | None = None) -> str:
    """The task of the run in ``run_dir`` as its config.json names it: "foveation" (the training command's
    default task, whose config names none) where it names none or there is no config.json. ``config``: the
    file as :func:`read_run_config` already read it (not read again)."""
    task = (config if config is not None else read_run_config(run_dir) or {}).get("task", "foveation")
    if not isinstance(task, str):
        raise ValueError(f"{Path(run_dir) / 'config.json'}: task {task!r} is not a task's name")
    return task


def task_command(task: str) -> str:
    """The training command of a task: ``python -m warp_vision.train`` and, but for foveation, the task."""
    return "python -m warp_vision.train" + ("" if task == "foveation" else f" {task}")


def checkpoint_path(run_dir, checkpoint: str = "best") -> Path:
    """RUN/best.pt or RUN/latest.pt (``checkpoint``); another name or a missing file is refused."""
    if checkpoint not in CHECKPOINTS:
        raise ValueError(f"checkpoint: expected one of {list(CHECKPOINTS)}, got {checkpoint!r}")
    path = Path(run_dir) / f"{checkpoint}.pt"
    if not path.exists():
        raise not_a_run(run_dir, path.name)
    return path


def not_a_run(run_dir, name: str) -> FileNotFoundError:
    """The error for ``run_dir`` without the file ``name`` a run directory holds. Where subdirectories
    hold it (as ``sim`` writes an eye's nets, e.g. runs/quick/pupil/left and .../right), it names them."""
    run_dir = Path(run_dir)
    runs = sorted(d.name for d in run_dir.iterdir() if (d / name).is_file()) if run_dir.is_dir() else []
    if runs:
        return FileNotFoundError(errno.ENOENT, f"holds the runs {', '.join(runs)}, not a run's {name}: name one, "
                                 f"e.g. {run_dir / runs[0]}", str(run_dir))
    return FileNotFoundError(errno.ENOENT, f"no {name}: is this a training run directory?", str(run_dir / name))


def net_from_checkpoint(ck: dict, device: str = "cpu", views: int | None = None,
                        source="checkpoint") -> torch.nn.Module:
    """The trained net of checkpoint ``ck`` (read from ``source``, named in errors), in eval mode. ``views``:
    a foveation CNN reads out by the consensus of that many views instead of its spec's (1: the plain image)."""
    if "net" not in ck:
        raise ValueError(f"{source}: holds no net spec (written by an older version; retrain it)")
    spec = ck["net"]
    if views is not None:
        if not (spec.get("kind") == "foveation" and spec.get("model") == "cnn"):
            raise ValueError(f"views: only the retina CNN (--model cnn) reads out by a consensus of views; {source} "
                             f"holds a {spec.get('kind')} {spec.get('model', '')} net")
        spec = {**spec, "views": views}
    model = build_net(spec, device)
    model.load_state_dict(ck["model"])
    return model.eval()


def load_net(path, device: str = "cpu", expect: dict | None = None) -> tuple[torch.nn.Module, dict]:
    """(the trained net in eval mode, the checkpoint) of a checkpoint file or of a run directory (its best.pt).
    ``expect``: what the net must belong to ({"task": "foveation", "eye": "right"}, as :func:`require_binding`
    reads it); a run directory's checkpoint must also belong to the run its config.json describes."""
    path = Path(path)
    run_dir = path if path.is_dir() else None
    if path.is_dir():
        path = path / "best.pt"
    ck = read_checkpoint(path, map_location=device)
    if expect:
        require_binding(ck, expect, path)
    config = read_run_config(run_dir) if run_dir is not None else None
    if config is not None:
        require_binding(ck, run_identity(saved_task(run_dir, config), config), path, f"the run in {run_dir}", config)
    return net_from_checkpoint(ck, device, source=path), ck


def _scale(onv: torch.Tensor, norm: dict):
    """The irradiance each ONV's responses are relative to: the training set's mean (a float), or with
    ``norm["per_sample"]`` each ONV's own mean ([B, 1], float32, accumulated without a float32 copy)."""
    if norm.get("per_sample", False):
        return onv.mean(dim=-1, keepdim=True, dtype=torch.float32).clamp_min(1e-12)
    return norm["input_scale"]


def net_input(onv: torch.Tensor, norm: dict, device, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """What a net trained on ONVs sees: a compressive (log) photoreceptor response,
    log(1 + irradiance / scale), standardised with the training set's mean and std over all inputs. The
    scale is the training set's mean irradiance, or, where ``norm["per_sample"]`` (v8 nets), each ONV's own
    mean irradiance: the photoreceptors adapt to the scene, so a room ten times brighter (or a wider
    pupil) gives the same responses. The log keeps dim surfaces and a lamp's hot spot in one range.
    One mean and std for every input keeps "brighter" meaning the same everywhere on the retina;
    standardising each input on its own turns a rarely lit peripheral photoreceptor's noise into large
    values.

    ``dtype`` is the net's (:func:`onv_dtype`). float32: the standardised response, float32. float16 or
    bfloat16: the response in that dtype, computed in one copy of the batch, and not standardised: the
    net's first layer does that (:meth:`warp_vision.nn.linet.LocallyConnected.fold_input_standardisation`),
    so no float32 copy of the batch is made."""
    scale = _scale(onv, norm)
    if torch.is_tensor(scale):
        scale = scale.to(device)
    if dtype != torch.float32:
        x = onv.to(device=device, dtype=dtype, copy=True)
        return x.div_(scale.to(dtype) if torch.is_tensor(scale) else scale).log1p_()
    x = torch.log1p(onv.to(device=device, dtype=torch.float32) / scale)
    return (x - norm["input_mean"].to(device)) / norm["input_std"].to(device)


@torch.no_grad()
def predict_targets(model: torch.nn.Module, onv: torch.Tensor, norm: dict, device, dtype: torch.dtype = torch.float32,
                    batch: int = 256) -> torch.Tensor:
    """A foveation-style net's predictions in the targets' units (e.g. yaw, pitch in radians) for ONVs
    [N, 3P], ``batch`` at a time: :func:`net_input`, the net, then its standardisation undone with
    ``norm["target_mean"]`` and ``norm["target_std"]``. [N, outputs] float32 on the CPU."""
    out = []
    for s in range(0, len(onv), batch):
        z = model(net_input(onv[s:s + batch], norm, device, dtype)).cpu()
        out.append(z * norm["target_std"] + norm["target_mean"])
    return torch.cat(out) if out else torch.zeros(0, len(norm["target_mean"]))


def fit_input_norm(onv16: torch.Tensor, train: np.ndarray, limit: int = 2000, per_sample: bool = False) -> dict:
    """The input normalisation of :func:`net_input` from (at most ``limit`` of) the training ONVs ``train``:
    {"input_scale": float, "per_sample": bool, "input_mean": 0-d tensor, "input_std": 0-d tensor}."""
    sub = onv16[torch.as_tensor(train[: min(len(train), limit)])].float()
    scale = float(sub.mean().clamp_min(1e-12))
    norm = {"input_scale": scale, "per_sample": bool(per_sample)}
    x = torch.log1p(sub / _scale(sub, norm))
    return {**norm, "input_mean": x.mean(), "input_std": x.std().clamp_min(1e-6)}
