"""The training loop: one view per step from a view sampler, a sum of loss terms, a densification
strategy, periodic held-out evaluation, resumable checkpoints, a NaN guard, PLY export and a JSON
log. The loop knows no model kind: `coin_cl.gs.model_kinds` builds the model, scales its schedules
and rebuilds it from a checkpoint (`model_from_state`); the default strategy and loss terms of a
kind come from `coin_cl.gs.strategy.default_strategy` and `coin_cl.gs.terms.default_terms`.
`make_trainer` joins the two over a loaded scene: the standard trainer, model kind from
`TrainConfig.model`. It lives here rather than beside the kinds because the loop already depends
on `model_kinds` (checkpoint loading), so the other way round would be an import cycle.

Output folder layout:
    ckpt.pt          last good checkpoint (written to a temporary file, fsynced, then renamed)
    log.json         config, per-interval losses and timings, evaluations, refinement events
    cameras.json     train/test cameras, so that `coin-cl render` needs no scene
    point_cloud.ply  final Gaussians (Scaffold-GS decoded to plain Gaussians)
"""

from __future__ import annotations

import json
import logging
import math
import os
import resource
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from coin_cl.checkpoint import CheckpointError, load_checkpoint, malformed
from coin_cl.gs import balance
from coin_cl.gs.base import Model
from coin_cl.gs.data import Camera, View, init_points, scene_extent
from coin_cl.gs.losses import LossConfig
from coin_cl.gs.model_kinds import ModelConfig, build_model, model_from_state, scaled_strategy
from coin_cl.gs.sampler import ShuffledEpochs, ViewSampler
from coin_cl.gs.strategy import Strategy, default_strategy
from coin_cl.gs.terms import LossContext, LossTerm, default_terms
from coin_cl.scene.io import atomic_write

log = logging.getLogger(__name__)

CKPT_NAME = "ckpt.pt"
# What to do with a ckpt.pt that cannot be resumed from (ends `CheckpointError`'s one line).
RESUME_REMEDY = (
    "delete it to train from the start (coin-cl train: --fresh; coin-cl run: --force the stage "
    "whose folder holds it)"
)
LOG_NAME = "log.json"
CAMERAS_NAME = "cameras.json"
PLY_NAME = "point_cloud.ply"


def ckpt_seconds_default() -> float:
    """Seconds between wall-time checkpoints: 60, or $COIN_CKPT_SECONDS (benchmarks/faults.py sets
    1 so that its kills land between checkpoints of its tiny runs)."""
    return float(os.environ.get("COIN_CKPT_SECONDS", 60.0))


class TrainingDivergedError(RuntimeError):
    """A loss, gradient or parameter became non-finite; training stopped without saving."""


@dataclass
class TrainConfig:
    model: str = "scaffold"
    iters: int = 30_000
    backend: str = "opencl"
    seed: int = 0
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    loss: LossConfig = field(default_factory=LossConfig)  # photometric term of `default_terms`
    eval_every: int = 0  # steps between held-out evaluations (0: only at the end)
    eval_at_seconds: tuple[float, ...] = ()  # also evaluate when training time crosses these
    ckpt_every: int = 1000  # steps between checkpoints (0: only at the end)
    # ... and at least every this many seconds of wall time (0: off), so that a kill loses at most
    # about a minute of work whatever the step rate (a checkpoint resumes bit-exactly, so when it
    # is written does not change the result).
    ckpt_seconds: float = field(default_factory=ckpt_seconds_default)
    log_every: int = 50
    max_seconds: float = 0.0  # stop when training time (evaluation excluded) exceeds this
    progress: bool = True  # tqdm bar
    export_ply: bool = True
    # The fused training path (index-gather decode, fused Adam); False: the earlier unfused path,
    # kept so that benchmarks/train.py --throughput measures both in one run. See docs/BENCHMARKS.md.
    fused: bool = True
    # Each auxiliary loss term's (`LossTerm.auxiliary`: the depth priors) root-mean-square gradient
    # is held to at most this times the photometric part's (`coin_cl.gs.balance`); 0: no cap.
    aux_grad_ratio: float = balance.RATIO
    # Steps between two measurements of one auxiliary term's gradient (each costs a backward pass).
    aux_measure_every: int = balance.EVERY


def _atomic_json(path: Path, obj: Any) -> None:
    text = json.dumps(obj, indent=1, default=_json_default)  # serialised before the file is opened
    atomic_write(path, lambda tmp: tmp.write_text(text))


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic | Tensor):
        return o.item() if getattr(o, "ndim", 0) == 0 else o.tolist()
    raise TypeError(f"not JSON-serialisable: {type(o)}")


def _state(obj: Any) -> dict[str, Any]:
    """`obj.state_dict()` for duck-typed parts that may not have one."""
    return obj.state_dict() if hasattr(obj, "state_dict") else {}


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def cameras_to_json(cams: Sequence[Camera]) -> list[dict]:
    return [c.to_json() for c in cams]


def cameras_from_json(items: list[dict]) -> list[Camera]:
    return [Camera.from_json(d) for d in items]


def evaluate_views(
    model: Model, views: Sequence[View], step: int, backend: str, background: Tensor
) -> dict[str, Any]:
    """Mean PSNR / SSIM (`coin_cl.metrics`: scikit-image SSIM) of renders over all pixels."""
    from coin_cl import metrics

    ps, ss = [], []
    with torch.no_grad():
        for v in views:
            out = model.render(v.camera, step, backend=backend, background=background)
            img = out.image.clamp(0, 1).numpy()
            gt = v.image.numpy()
            ps.append(metrics.psnr(img, gt))
            ss.append(metrics.ssim(img, gt))
    return {"psnr": float(np.mean(ps)) if ps else math.nan,
            "ssim": float(np.mean(ss)) if ss else math.nan, "psnr_views": ps}  # fmt: skip


class Trainer:
    """Train `model` on `train_views`, evaluating on `test_views`.

    One step: `sampler.next()` picks a view; every term's `before_render` may add keyword
    arguments to the render (`return_depth`, a `features` override); the model renders it;
    `strategy.step_pre_backward`; total = sum(term.weight * term(ctx)), the auxiliary terms
    scaled by `AuxBalance` (`coin_cl.gs.balance`); backward; NaN guard; the model's optimiser
    step; every term's `step_after(ctx)`; `strategy.step_post_backward` (statistics,
    densification).

    Args:
        strategy: densification (default: `default_strategy(model.kind)`, the published
            schedule; `scaled_strategy` fits it to a short run). Initialised here with cfg.seed.
        terms: loss terms, unique names (default: `default_terms(model.kind, cfg.loss)`).
        sampler: view order (default: `ShuffledEpochs` seeded with cfg.seed + 1).
        out_dir: where checkpoints, the log and the PLY go (None: nothing is written).
        callback: called as callback(trainer, step) at the start of every step (tests use it
            to kill or poison a run).
    """

    def __init__(
        self,
        model: Model,
        train_views: Sequence[View],
        test_views: Sequence[View],
        cfg: TrainConfig,
        out_dir: str | Path | None = None,
        callback: Callable[[Trainer, int], None] | None = None,
        *,
        strategy: Strategy | None = None,
        terms: Sequence[LossTerm] | None = None,
        sampler: ViewSampler | None = None,
    ):
        if not train_views:
            raise ValueError("no training views")
        self.model = model
        self.train_views = list(train_views)
        self.test_views = list(test_views)
        self.cfg = cfg
        self._set_path(model)
        self.out = Path(out_dir) if out_dir is not None else None
        self.callback = callback
        self.background = torch.tensor(cfg.background, dtype=torch.float32)
        self.step = 0
        self.train_seconds = 0.0
        self.strategy = strategy if strategy is not None else default_strategy(model.kind)
        # What the images can show: the strategy's size cap is per training pixel.
        self.train_pixels = sum(v.camera.width * v.camera.height for v in self.train_views)
        self.strategy.initialize(model, seed=cfg.seed, train_pixels=self.train_pixels)
        self.terms = list(terms) if terms is not None else default_terms(model.kind, cfg.loss)
        names = [t.name for t in self.terms]
        if not names:
            raise ValueError("no loss terms")
        if len(set(names)) != len(names):
            raise ValueError(f"loss term names must be unique (they key checkpoints): {names}")
        # seed + 1: the view order stream of earlier versions, so old runs replay identically.
        self.sampler = sampler if sampler is not None else ShuffledEpochs(len(self.train_views), cfg.seed + 1)
        self.log: dict[str, Any] = {"config": asdict(cfg), "train": [], "eval": [], "refine": []}
        # What else shaped the run, for the record (the loop's own settings are in "config").
        self.log["strategy"] = {"kind": type(self.strategy).__name__, **self.strategy.config(),
                                "train_pixels": self.train_pixels,
                                "size_limit": self.strategy.size_limit(model)}  # fmt: skip
        self.log["terms"] = {t.name: t.weight for t in self.terms}
        self.balance = balance.AuxBalance(cfg.aux_grad_ratio, cfg.aux_measure_every)
        self._evals_done: set[float] = set()
        self._acc: dict[str, float] = {}  # loss sums of the current log interval
        self._n_acc = 0
        self._last_ckpt = time.monotonic()
        if self.out is not None:
            self.out.mkdir(parents=True, exist_ok=True)
            cams = {"train": cameras_to_json([v.camera for v in self.train_views]),
                    "test": cameras_to_json([v.camera for v in self.test_views])}  # fmt: skip
            _atomic_json(self.out / CAMERAS_NAME, cams)

    def _set_path(self, model: Model) -> None:
        """The training path of `cfg.fused` on the model and its optimiser (a checkpoint load
        builds a new model, so this runs again there)."""
        model.fused = model.optimizer.fused = self.cfg.fused

    # ---- checkpoints ----
    @property
    def ckpt_path(self) -> Path | None:
        return None if self.out is None else self.out / CKPT_NAME

    def save_checkpoint(self) -> None:
        """Write the whole training state to ckpt.pt, atomically (`coin_cl.atomic`)."""
        if self.out is None:
            return
        self._last_ckpt = time.monotonic()
        state = {
            "model": self.model.state_dict(),
            "strategy": self.strategy.state_dict(),
            "terms": {t.name: _state(t) for t in self.terms},
            "sampler": self.sampler.state_dict(),
            "trainer": {
                "step": self.step,
                "train_seconds": self.train_seconds,
                "log": self.log,
                "evals_done": sorted(self._evals_done),
                # the running means of the current log interval, so a resumed log is the same
                "acc": dict(self._acc),
                "n_acc": self._n_acc,
                "balance": self.balance.state_dict(),
            },
        }
        atomic_write(self.out / CKPT_NAME, lambda tmp: torch.save(state, tmp))
        self.save_log()

    def load_checkpoint(self, path: str | Path | None = None) -> None:
        """Restore model, optimizer, strategy, loss terms, sampler and log from a checkpoint
        (default out_dir/ckpt.pt). The checkpoint's model and strategy settings win."""
        path = Path(path) if path is not None else self.ckpt_path
        if path is None or not path.is_file():
            raise FileNotFoundError(f"no checkpoint at {path}")
        state = load_checkpoint(path, RESUME_REMEDY)
        try:
            self._restore(state)
        except (KeyError, TypeError, AttributeError, IndexError) as exc:  # a dict of another shape
            raise malformed(path, exc, RESUME_REMEDY) from None

    def _restore(self, state: dict[str, Any]) -> None:
        msd = state["model"]
        device = self.model.device  # the device is the caller's choice, not the checkpoint's
        self.model = model_from_state(msd)
        self.model.device = device
        self._set_path(self.model)
        t = state["trainer"]
        # Checkpoints from before the strategy / sampler split kept these in the model and trainer.
        legacy_cfg = {**msd.get("cfg", {}), **msd.get("cfg", {}).get("densify", {})}
        sst = state.get("strategy") or {"config": legacy_cfg, "stats": msd["stats"], "gen": msd["gen"]}
        self.strategy.initialize(self.model, seed=self.cfg.seed, train_pixels=self.train_pixels)
        self.strategy.load_state_dict(sst)
        saved = state.get("terms", {})
        for term in self.terms:
            if term.name in saved and hasattr(term, "load_state_dict"):
                term.load_state_dict(saved[term.name])
        unused = sorted(set(saved) - {t.name for t in self.terms})
        if unused:
            log.warning("checkpoint has state for loss terms this trainer lacks: %s", unused)
        self.sampler.load_state_dict(state.get("sampler") or {"gen": t["gen"], "perm": t["perm"]})
        self.step = int(t["step"])
        self.train_seconds = float(t["train_seconds"])
        self.log = t["log"]
        self._evals_done = set(t["evals_done"])
        self._acc, self._n_acc = dict(t.get("acc", {})), int(t.get("n_acc", 0))
        self.balance.load_state_dict(t.get("balance", {}))

    def save_log(self) -> None:
        if self.out is not None:
            self.log["peak_rss_mb"] = _peak_rss_mb()
            _atomic_json(self.out / LOG_NAME, self.log)

    # ---- loop ----
    def _diverged(self, what: str) -> TrainingDivergedError:
        last = "none was written"
        if self.ckpt_path is not None and self.ckpt_path.is_file():
            try:
                st = load_checkpoint(self.ckpt_path)["trainer"]["step"]
                last = f"{self.ckpt_path} (after step {st}) is kept"
            except (CheckpointError, KeyError, TypeError):
                last = f"{self.ckpt_path} is unreadable"
        self.log["diverged"] = {"step": self.step, "what": what}
        self.save_log()
        return TrainingDivergedError(
            f"training diverged: non-finite {what} at step {self.step}; stopped without saving. "
            f"Last good checkpoint: {last}. Try a lower learning rate or another seed."
        )

    def _check_finite(self, loss: Tensor) -> None:
        if not torch.isfinite(loss):
            raise self._diverged("loss")
        for name, p in self.model.optimizer.params.items():
            if p.grad is not None and not torch.isfinite(p.grad.sum()):
                raise self._diverged(f"gradient of {name}")
            if not torch.isfinite(p.detach().sum()):
                raise self._diverged(f"parameter {name}")

    def _render_kwargs(self, view: View, idx: int, model: Model) -> dict[str, Any]:
        """Extra `model.render` keyword arguments the terms ask for this step (`before_render`:
        depth on a reference view, attended features); two terms may ask for the same flag
        (`return_depth=True` from two depth terms) but may not set one argument to different values."""
        extra: dict[str, Any] = {}
        for term in self.terms:
            if not hasattr(term, "before_render"):
                continue
            kw = term.before_render(view, idx, self.step, model) or {}
            clash = sorted(k for k in set(kw) & set(extra) if not _same(kw[k], extra[k]))
            if clash:
                raise ValueError(f"loss term {term.name!r} sets render arguments already set: {clash}")
            extra.update(kw)
        return extra

    def train_step(self) -> dict[str, float]:
        """One optimisation step on the next view; returns the loss parts and timings."""
        idx = self.sampler.next()
        view = self.train_views[idx]
        m = self.model
        t0 = time.perf_counter()
        extra = self._render_kwargs(view, idx, m)
        out = m.render(view.camera, self.step, backend=self.cfg.backend,
                       background=self.background, training=True, **extra)  # fmt: skip
        self.strategy.step_pre_backward(m, self.step, out)
        ctx = LossContext(view=view, index=idx, out=out, step=self.step, model=m)
        values: dict[str, float] = {}
        main: Tensor | None = None
        aux: dict[str, Tensor] = {}
        for term in self.terms:
            v = term.weight * term(ctx)
            values[term.name] = float(v.detach())
            if getattr(term, "auxiliary", False):
                aux[term.name] = v
            else:
                main = v if main is None else main + v
        total = main
        if aux:  # the parameters and retained gradients a measurement needs, only where one may come
            params = [p for p in m.optimizer.params.values() if p.requires_grad]
            m2d = out.meta.get("means2d")
            retained = [m2d] if isinstance(m2d, Tensor) and m2d.requires_grad else []
            for name, v in self.balance.weigh(self.step, main, aux, params, retained).items():
                values[f"{name}_scale"] = self.balance.scale.get(name, 1.0)
                total = v if total is None else total + v
        assert total is not None  # __init__ requires a term
        t1 = time.perf_counter()
        m.optimizer.zero_grad()
        total.backward()
        t2 = time.perf_counter()
        self._check_finite(total.detach())
        m.optimizer.step(self.step)
        for term in self.terms:
            if hasattr(term, "step_after"):
                term.step_after(ctx)
        t3 = time.perf_counter()
        events = self.strategy.step_post_backward(m, self.step, out)
        t4 = time.perf_counter()
        if any(events.values()):
            self.log["refine"].append({"step": self.step + 1, **events, "n": m.n_primitives})
        return {
            "loss": float(total.detach()),
            **values,
            **ctx.log,
            "t_fwd": t1 - t0,
            "t_bwd": t2 - t1,
            "t_opt": t3 - t2,
            "t_refine": t4 - t3,
            "n_drawn": int(out.meta["visible"].sum()),
        }

    def evaluate(self) -> dict[str, Any]:
        """Held-out PSNR/SSIM now; appended to the log with the training time so far."""
        t = time.perf_counter()
        res = evaluate_views(self.model, self.test_views, self.step, self.cfg.backend,
                             self.background)  # fmt: skip
        entry = {"step": self.step, "train_seconds": self.train_seconds,
                 "eval_seconds": time.perf_counter() - t, "n": self.model.n_primitives, **res}  # fmt: skip
        self.log["eval"].append(entry)
        log.info("step %d (%.0f s): held-out PSNR %.2f dB SSIM %.4f", self.step,
                 self.train_seconds, res["psnr"], res["ssim"])  # fmt: skip
        self.save_log()
        return entry

    def train(self) -> dict[str, Any]:
        """Run until `iters` steps (or `max_seconds` of training); returns the final summary."""
        cfg = self.cfg
        if self.step == 0 and self.out is not None and not self.ckpt_path.is_file():
            self.save_checkpoint()  # a last good state exists from the very start
        bar = None
        if cfg.progress:
            from tqdm import tqdm

            bar = tqdm(total=cfg.iters, initial=self.step, desc=f"train {self.model.kind}",
                       dynamic_ncols=True)  # fmt: skip
        self._last_ckpt = time.monotonic()
        try:
            while self.step < cfg.iters:
                if cfg.max_seconds and self.train_seconds >= cfg.max_seconds:
                    log.info("time budget of %.0f s reached at step %d", cfg.max_seconds, self.step)
                    break
                if self.callback is not None:
                    self.callback(self, self.step)
                t = time.perf_counter()
                rec = self.train_step()
                self.train_seconds += time.perf_counter() - t
                self.step += 1
                for k, v in rec.items():
                    self._acc[k] = self._acc.get(k, 0.0) + v
                self._n_acc += 1
                if self.step % cfg.log_every == 0 or self.step == cfg.iters:
                    mean = {k: v / self._n_acc for k, v in self._acc.items()}
                    self.log["train"].append({"step": self.step, "train_seconds": self.train_seconds,
                                              "n": self.model.n_primitives, **mean})  # fmt: skip
                    if bar is not None:
                        bar.set_postfix(loss=f"{mean['loss']:.4f}", n=self.model.n_primitives)
                    self._acc, self._n_acc = {}, 0
                if bar is not None:
                    bar.update(1)
                due = [s for s in cfg.eval_at_seconds
                       if s not in self._evals_done and self.train_seconds >= s]  # fmt: skip
                if due or (cfg.eval_every and self.step % cfg.eval_every == 0):
                    self._evals_done.update(due)
                    if self.test_views:
                        self.evaluate()
                if (cfg.ckpt_every and self.step % cfg.ckpt_every == 0) or (
                    cfg.ckpt_seconds and time.monotonic() - self._last_ckpt >= cfg.ckpt_seconds
                ):
                    self.save_checkpoint()
        finally:
            if bar is not None:
                bar.close()
        final: dict[str, Any] = {}
        if self.test_views:
            last = self.log["eval"][-1] if self.log["eval"] else None
            final = last if last is not None and last["step"] == self.step else self.evaluate()
        self.save_checkpoint()
        if cfg.export_ply and self.out is not None:
            self.export_ply(self.out / PLY_NAME)
        return {"step": self.step, "train_seconds": self.train_seconds,
                "n": self.model.n_primitives, **final}  # fmt: skip

    def export_ply(self, path: Path) -> None:
        """Write the model as plain 3DGS Gaussians, view-dependent colours frozen at the mean
        training camera (`Model.export_gaussians`, `Splats.to_ply`)."""
        center = torch.stack([v.camera.center_t for v in self.train_views]).mean(0)
        self.model.export_gaussians(center).to_ply(path)


def make_trainer(
    scene,
    train_idx: Sequence[int],
    test_idx: Sequence[int],
    cfg: TrainConfig,
    out_dir: str | Path | None = None,
    train_images: Sequence | None = None,
    model_cfg: ModelConfig | None = None,
    exclude_masks: bool = False,
    resume: bool = True,
    device=None,
    strategy: Strategy | None = None,
    terms: Sequence[LossTerm] | None = None,
    sampler: ViewSampler | None = None,
) -> Trainer:
    """A trainer over a loaded scene; resumes from out_dir/ckpt.pt when it exists and `resume`.

    train_images: replacement targets for the training views (e.g. per-view inpaints).
    device: the OpenCL device the model renders on (a Runtime or a name; default device if None).
    strategy: default `scaled_strategy(cfg.model, cfg.iters)`, the schedule every caller got
        before densification left the model config; terms / sampler: see `Trainer`.
    """
    from coin_cl.gs.data import views_from_scene

    train = views_from_scene(scene, train_idx, train_images, exclude_masks=exclude_masks)
    test = views_from_scene(scene, test_idx)
    pts, cols = init_points(scene, train)
    extent = scene_extent([v.camera for v in train])
    model = build_model(cfg.model, pts, cols, extent, cfg.seed, model_cfg)
    model.device = device
    if strategy is None:
        strategy = scaled_strategy(cfg.model, cfg.iters)
    tr = Trainer(model, train, test, cfg, out_dir, strategy=strategy, terms=terms, sampler=sampler)
    if resume and tr.ckpt_path is not None and tr.ckpt_path.is_file():
        tr.load_checkpoint()
        log.info("resumed from %s at step %d", tr.ckpt_path, tr.step)
    return tr


def _same(a: Any, b: Any) -> bool:
    """Two render arguments agree: the same object, or equal plain values (flags, numbers)."""
    return a is b or (isinstance(a, (bool, int, float, str)) and type(a) is type(b) and a == b)
