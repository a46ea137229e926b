"""State of one service instance (settings, model, cache, metrics) and the steps a request
takes: bring the image to the model's camera, place each grasp's crop window, encode the
windows not yet cached (one batched encoder call), score, flag what the model never saw,
calibrate."""

from __future__ import annotations

import gc
import logging
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass

import anyio
import numpy as np

from vgq.camera import DEFAULT_TILT_RANGE, describe_level, map_pixels, tilt_outside_training
from vgq.crop import (
    grid_window_centers,
    in_training_range,
    window_center,
    window_origin,
)
from vgq.grasps import GraspError, pose_rows
from vgq.ood import flag_names, ood_flags
from vgq.pose import roll_quaternions
from vgq.turns import pose_jaw_angles, turn_index, turned_view

from . import logs
from . import placement as image_placement
from .cache import CachedImage, EncodedWindow, MemoryCache
from .camera import client_camera, client_level, to_model_camera
from .config import Settings
from .errors import ApiError
from .metrics import Metrics
from .preprocess import window_input, window_missing
from .runtime import FastModel


def grasp_error(e: GraspError) -> ApiError:
    """The contract's GraspError as the HTTP edge answers it: 422 naming the rows."""
    return ApiError(422, str(e), {"grasps": e.indices} if e.indices else None)


@dataclass(frozen=True)
class Scores:
    """What one score request produced, per grasp in request order."""

    p_success: np.ndarray  # (k,) float64: calibrated P(success) (the raw score when the model has no calibration)
    raw_score: np.ndarray  # (k,) float32: the network's output
    ood_mask: np.ndarray  # (k,) uint8 bitmask of vgq.ood.OOD_FLAGS
    windows: int  # crop windows the grasps fell in
    windows_encoded: int  # of them, encoded by this request (the rest were cached)
    missing_fraction: float  # largest share of missing depth among those windows
    #: a placement model's only: (k,) bool, the grasps whose placement row is known (table and object
    #: region found at the grasp), and whether the image showed a table; None for any other model
    placement_known: np.ndarray | None = None
    table_found: bool | None = None

    def ood(self) -> list[list[str]]:
        return [list(FLAG_NAMES[m]) for m in self.ood_mask.tolist()]


#: flag names of every uint8 mask (one look-up per grasp in a JSON answer)
FLAG_NAMES = tuple(tuple(flag_names(m)) for m in range(256))


@contextmanager
def _client_rows(ix: np.ndarray):
    """A 422 raised for a subset of the grasps (rows ``ix`` of the request) names the request's rows."""
    try:
        yield
    except ApiError as e:
        if e.details and "grasps" in e.details:
            e.details = {**e.details, "grasps": ix[np.asarray(e.details["grasps"], dtype=np.intp)].tolist()}
        raise


def _with_placement(rows: np.ndarray, extra: np.ndarray) -> np.ndarray:
    """A placement head's pose rows: the (k, 7) network pose rows, each followed by its grasp's
    placement row (``extra`` (k, 7), ``vgq.placement``)."""
    return np.ascontiguousarray(np.hstack([rows, extra]), dtype=np.float32)


def window_groups(origins: np.ndarray) -> tuple[dict, np.ndarray]:
    """Grasps by crop window: ``{origin (u, v): indices of its grasps, ascending}`` in sorted
    origin order, and the (k,) position of each grasp's window in that order. ``origins``
    (k, 2) int64, k >= 1. All in one window (the usual case) skips the sort."""
    first = origins[0]
    if (origins == first).all():
        k = len(origins)
        return {(int(first[0]), int(first[1])): np.arange(k)}, np.zeros(k, np.intp)
    uniq, inverse = np.unique(origins, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(inverse, kind="stable")
    groups = np.split(order, np.cumsum(np.bincount(inverse, minlength=len(uniq)))[:-1])
    return {(int(o[0]), int(o[1])): ix for o, ix in zip(uniq, groups)}, inverse


class Service:
    """State of one service instance: settings, model, cache, metrics."""

    def __init__(self, settings: Settings, model: FastModel | None = None, cache=None):
        self.settings = settings
        self.log = logs.setup(settings.log_level)
        self.model = model
        self.cache = cache if cache is not None else make_cache(settings, self.log)
        self.metrics = Metrics(self.cache)
        self.ready = False
        self.load_error: str | None = None
        self.calibration = None
        self.z_range, self.z_range_source = (0.0, np.inf), ""
        self.tilt_range = DEFAULT_TILT_RANGE
        #: the head reads a placement row after each grasp's pose columns (``service.placement``)
        self.placement = False
        #: a placement model's: the one-shot route's image analysis, beside the encoder (started at load)
        self._analyser: ThreadPoolExecutor | None = None
        # bounds the plans computed at once (service/plan_routes.py); a waiting plan holds no thread
        self.plan_slots = anyio.CapacityLimiter(settings.max_concurrent_plans)

    def load(self) -> None:
        """Load (unless given) and warm up the model; then mark ready."""
        try:
            if self.model is None:
                self.model = FastModel(
                    self.settings.model_dir,
                    threads=self.settings.ort_threads,
                    head_precision=self.settings.head_precision,
                    encoder_precision=self.settings.encoder_precision,
                )
            self.calibration = self.model.card.calibrator()
            self.z_range, self.z_range_source = self.model.card.z_range()
            self.tilt_range = self.model.card.tilt_range()
            self.placement = bool(self.model.card.placement_columns)
            if self.placement and self._analyser is None:
                self._analyser = ThreadPoolExecutor(1, thread_name_prefix="vgq-placement")
            self.model.warm_up()
            gc.collect()
            gc.freeze()  # start-up objects out of the collector's way: no GC pauses on them later
            self.ready = True
            self.metrics.ready.set(1)
            logs.event(
                self.log,
                "ready",
                model_version=self.model.version,
                head=self.model.head_precision,
                encoder=self.model.encoder_info,
                threads=self.settings.ort_threads,
                cache=self.cache.backend,
                calibrated=self.calibration is not None,
            )
        except Exception as e:  # reported by /readyz and the log; the process stays up for diagnosis
            self.load_error = str(e)
            logs.event(self.log, "model load failed", logging.ERROR, error=str(e))

    # ---- upload ---------------------------------------------------------------------------------
    def prepare_image(self, depth: np.ndarray, numbers: dict) -> CachedImage:
        """An upload as the cache keeps it: resampled to the model's focal lengths, windows not
        yet encoded; with ``center_u`` / ``center_v`` (client px) its one fixed window placed."""
        model = self.model.card.intrinsics
        camera, assumed = client_camera(numbers, depth.shape, model)
        up, roll, up_from = client_level(numbers, depth, camera)
        cu, cv = numbers.get("center_u"), numbers.get("center_v")
        if cu is not None or cv is not None:
            h, w = depth.shape
            cu = (w - 1) / 2 if cu is None else cu
            cv = (h - 1) / 2 if cv is None else cv
            if not (0 <= cu <= w - 1 and 0 <= cv <= h - 1):
                raise ApiError(
                    422,
                    f"window centre ({cu}, {cv}) must lie inside the {h}x{w} image "
                    f"(u in [0, {w - 1}], v in [0, {h - 1}])",
                )
        resampled_depth, resampled = to_model_camera(depth, camera, model, self.settings.max_image_side, assumed, roll)
        entry = CachedImage(resampled_depth, camera, resampled, assumed, up=up, roll=roll, up_from=up_from)
        if cu is not None:
            c = map_pixels([[cu, cv]], camera, resampled, roll)[0]
            geom = self.model.geometry
            origin = window_origin(c, geom)
            entry.fixed_center = window_center(origin, geom)
        return entry

    def encode_fixed_window(self, entry: CachedImage) -> None:
        """Encode the fixed window of ``entry`` (if it has one) now: 422 when mostly missing."""
        if entry.fixed_center is not None and not entry.windows:
            o = window_origin(entry.fixed_center, self.model.geometry)
            new = self._encode({(int(o[0]), int(o[1])): None}, entry, {})
            entry.windows.update(new)

    def analyse_placement(
        self, entry: CachedImage, depth: np.ndarray, key: str | None = None, placed: tuple | None = None
    ) -> int:
        """For a model whose head reads placement rows: analyse ``depth``, the upload of ``entry`` as
        decoded (metres, client pixels, before resampling or inpainting), with the upload's own
        intrinsics, and keep the analysis with the entry. Nothing for any other model.

        ``key`` and ``placed`` (a one-shot's grasps, :meth:`place`): the analysis runs in a helper
        thread while their windows of ``entry`` are encoded here (onnxruntime lets go of the GIL), so
        the call costs about the longer of the two rather than their sum; the scoring that follows
        finds the windows encoded (a 422 for a mostly missing window comes from here). Returns the
        number of windows encoded here."""
        if not self.placement or entry.placement is not None:
            return 0
        if placed is None or self._analyser is None or self.model.geometry.jaw_turns:
            entry.placement = image_placement.analyse(depth, entry.camera)
            return 0
        job = self._analyser.submit(image_placement.analyse, depth, entry.camera)
        try:
            where = window_groups(placed[1])[0]
            return len(self._encode_new(key, entry, where, [o for o in where if o not in entry.windows]))
        finally:
            entry.placement = job.result()

    def put(self, key: str, entry: CachedImage) -> None:
        self.cache.put(key, entry)

    # ---- scoring --------------------------------------------------------------------------------
    def place(self, entry: CachedImage, grasps: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Check (k, 7) client grasps against ``entry``: (pose rows (k, 7) float32, window
        origins (k, 2) int64 in the resampled image, the grasps (k, 7) float64 with (u, v) in
        the resampled image). Raises 422."""
        g = np.asarray(grasps, dtype=np.float64)
        if g.ndim != 2 or g.shape[1] != 7:
            raise grasp_error(GraspError(f"grasps must be (k, 7) rows u, v, z, qw, qx, qy, qz; got shape {g.shape}"))
        geom = self.model.geometry
        uv = map_pixels(g[:, :2], entry.camera, entry.resampled, entry.roll)
        mapped = g.copy()
        mapped[:, :2] = uv
        if entry.roll != 0.0:  # orientations in the level camera's frame
            mapped[:, 3:7] = roll_quaternions(g[:, 3:7], entry.roll)
        finite = np.isfinite(uv)
        if finite.all():  # the usual case: no row to set aside
            finite, safe = True, uv
        else:  # rows with a non-finite (u, v) are left to pose_rows, which names them
            finite = finite.all(axis=1)
            safe = np.where(finite[:, None], uv, 0.0)
        if entry.fixed_center is not None:
            centres = np.broadcast_to(entry.fixed_center, safe.shape)
            bad = finite & ~in_training_range(safe, entry.fixed_center, geom)
            if bad.any():
                r = self.grasp_range(entry)
                turned = (
                    f" (a square turned by the camera's roll of {np.degrees(entry.roll):.1f} deg: its bounding box)"
                    if entry.roll != 0.0
                    else ""
                )
                raise ApiError(
                    422,
                    f"{int(bad.sum())} grasps lie outside the window the model was trained for: u in "
                    f"[{r['u'][0]:g}, {r['u'][1]:g}], v in [{r['v'][0]:g}, {r['v'][1]:g}] (image px){turned}; upload "
                    "without center_u / center_v to have windows placed for every grasp",
                    {"grasps": np.flatnonzero(bad)[:20].tolist()},
                )
        else:
            h, w = entry.image_shape
            client = g[:, :2]
            if not ((client >= -0.5) & (client <= (w - 0.5, h - 0.5))).all():  # some row outside, or not finite
                u, v = g[:, 0], g[:, 1]
                bad = finite & ~((u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5))
                if bad.any():
                    raise ApiError(
                        422,
                        f"{int(bad.sum())} grasps lie outside the {h}x{w} image (u in [-0.5, {w - 0.5}], "
                        f"v in [-0.5, {h - 0.5}] px)",
                        {"grasps": np.flatnonzero(bad)[:20].tolist()},
                    )
            centres = grid_window_centers(safe, entry.depth.shape, geom)
        try:
            # every window was placed above within kappa of its grasps: pose_rows need not check that again
            rows = pose_rows(mapped, centres, geom, self.settings.max_grasps, check_window=False)
        except GraspError as e:
            raise grasp_error(e) from None
        return rows, window_origin(centres, geom), mapped

    def _encode(self, wanted: dict, entry: CachedImage, where: dict) -> dict:
        """Encode the windows ``wanted`` (origin -> None) of ``entry`` in one encoder call.
        ``where``: origin -> grasp indices (named in a 422). Returns origin -> EncodedWindow."""
        geom, cap = self.model.geometry, self.settings.max_missing_fraction
        origins, crops, missing = list(wanted), [], []
        for o in origins:
            try:
                win = window_input(entry.depth, o, geom, cap, entry.outside())
            except ApiError as e:
                if o in where:
                    e.details = {**e.details, "grasps": where[o][:20].tolist()}
                raise
            crops.append(win.image)
            missing.append(win.missing_fraction)
        if not origins:
            return {}
        terms = self.model.encode(np.stack(crops))
        self.metrics.encoder.observe(self.model.encode_seconds)
        self.metrics.windows_encoded.inc(len(origins))
        return {o: EncodedWindow(terms[i : i + 1].copy(), m) for i, (o, m) in enumerate(zip(origins, missing))}

    def score(
        self, key: str, entry: CachedImage, grasps: np.ndarray, strict: bool = False, placed: tuple | None = None
    ) -> Scores:
        """Score (k, 7) client grasps against ``entry`` (cached as ``key``). ``placed``: what
        ``place(entry, grasps)`` returned, when the caller placed them already. A model trained
        on windows turned towards the jaw (``CropGeometry.jaw_turns``) scores each grasp in the
        image turned by its turn (:meth:`turned_entry`)."""
        placed = placed if placed is not None else self.place(entry, grasps)
        if self.model.geometry.jaw_turns:
            return self._score_turned(key, entry, grasps, strict, placed)
        # windows and flags before any encoding: a strict request that fails costs no inference
        looked = self._windows_and_flags(key, entry, placed)
        if strict:
            self._refuse_ood(looked[3])
        if not self.placement:
            raw, encoded = self._infer(key, entry, placed[0], looked)
            return self._scores(raw, looked[3], len(looked[0]), encoded, max(looked[2].values()))
        extra = image_placement.rows(entry.placement, grasps)
        raw, encoded = self._infer(key, entry, _with_placement(placed[0], extra), looked)
        return self._scores(raw, looked[3], len(looked[0]), encoded, max(looked[2].values()), entry, extra)

    def _score_turned(self, key: str, entry: CachedImage, grasps: np.ndarray, strict: bool, placed: tuple) -> Scores:
        """:meth:`score` for a model of windows turned towards the jaw: each turn's grasps on its
        turned image (:meth:`turned_entry`)."""
        jobs = self._turned_jobs(key, entry, grasps, placed)
        looked = [self._windows_and_flags(k, e, p) for k, e, _, p in jobs]
        mask = np.empty(len(placed[0]), np.uint8)
        for (_, _, ix, _), w in zip(jobs, looked):
            mask[ix] = w[3]
        if strict:
            self._refuse_ood(mask)
        # placement rows from the grasps as sent, in the upload's camera (frame-invariant geometry)
        extra = image_placement.rows(entry.placement, grasps) if self.placement else None
        raw, encoded = np.empty(len(mask), np.float32), 0
        for (k, e, ix, p), w in zip(jobs, looked):
            with _client_rows(ix):
                rows = p[0] if extra is None else _with_placement(p[0], extra[ix])
                raw[ix], n = self._infer(k, e, rows, w)
            encoded += n
        windows = sum(len(w[0]) for w in looked)
        missing = max(max(w[2].values()) for w in looked)
        return self._scores(raw, mask, windows, encoded, missing, entry if extra is not None else None, extra)

    def _scores(
        self,
        raw: np.ndarray,
        mask: np.ndarray,
        windows: int,
        encoded: int,
        missing: float,
        entry: CachedImage | None = None,
        extra: np.ndarray | None = None,
    ) -> Scores:
        """``entry`` and ``extra`` (its grasps' placement rows): a placement model's only."""
        self.metrics.grasps.observe(len(raw))
        p = self.calibration.apply(raw) if self.calibration is not None else raw.astype(np.float64)
        if extra is None:
            return Scores(p, raw, mask, windows, encoded, float(missing))
        table = image_placement.describe(entry.placement)["table_found"]
        return Scores(p, raw, mask, windows, encoded, float(missing), extra[:, 0] > 0, table)

    @staticmethod
    def _refuse_ood(mask: np.ndarray) -> None:
        """422 naming the grasps whose OOD ``mask`` (k,) is set (a strict request)."""
        if mask.any():
            bad = np.flatnonzero(mask)
            raise ApiError(
                422,
                f"{len(bad)} grasps are outside what the model was trained on (strict=true): "
                + "; ".join(f"{i}: {', '.join(flag_names(mask[i]))}" for i in bad[:5]),
                {"grasps": bad[:20].tolist(), "ood": {str(i): flag_names(mask[i]) for i in bad[:20]}},
            )

    def _windows_and_flags(self, key: str, entry: CachedImage, placed: tuple) -> tuple:
        """For grasps ``placed`` in ``entry``: (windows {origin: grasp indices}, the windows not yet
        encoded, the missing fraction of each window, OOD masks (k,) uint8). Fetches windows held
        by another replica."""
        rows, origins, mapped = placed
        where, inverse = window_groups(origins)
        new = [o for o in where if o not in entry.windows]
        if new:
            self.cache.fetch_windows(key, entry, new)
            new = [o for o in new if o not in entry.windows]
        geom, cap = self.model.geometry, self.settings.ood_window_missing
        outside = entry.outside()
        frac = {
            o: entry.windows[o].missing_fraction
            if o in entry.windows
            else window_missing(entry.depth, o, geom, outside)
            for o in where
        }
        if len(where) == 1:
            win_missing = next(iter(frac.values())) > cap  # one bool for every grasp
        else:
            win_missing = np.array([frac[o] > cap for o in where], dtype=bool)[inverse]
        mask = ood_flags(
            mapped, entry.depth, self.z_range, win_missing, tilt_outside_training(entry.up, self.tilt_range)
        )
        return where, new, frac, mask

    def _encode_new(self, key: str, entry: CachedImage, where: dict, new: list) -> dict:
        """Encode the windows ``new`` of ``entry`` (cached as ``key``) in one encoder call and keep
        them with it (``where``: origin -> grasp indices, named in a 422); the windows encoded."""
        encoded = self._encode(dict.fromkeys(new), entry, where) if new else {}
        if encoded:
            self.cache.add_windows(key, entry, encoded)
        return encoded

    def _infer(self, key: str, entry: CachedImage, rows: np.ndarray, looked: tuple) -> tuple[np.ndarray, int]:
        """Encode the new windows of ``looked`` (:meth:`_windows_and_flags`), then run the head on
        the pose ``rows`` (k, 7; k, 14 for a placement head: :func:`_with_placement`): (raw scores
        (k,) float32, windows encoded)."""
        where, new = looked[0], looked[1]
        encoded = self._encode_new(key, entry, where, new)
        if len(where) == 1:  # one window: its rows as they are, no gather and scatter
            raw = np.asarray(self.model.score(entry.windows[next(iter(where))].term, rows), np.float32).reshape(-1)
            self.metrics.head.observe(self.model.score_seconds)
        else:
            raw = np.empty(len(rows), np.float32)
            for o, ix in where.items():
                raw[ix] = self.model.score(entry.windows[o].term, rows[ix])
                self.metrics.head.observe(self.model.score_seconds)
        return raw, len(encoded)

    # ---- windows turned towards the jaw ----------------------------------------------------------
    def turned_entry(self, key: str, entry: CachedImage, turn: int) -> tuple[str, CachedImage]:
        """The image of ``entry`` turned by turn ``turn`` of the model's ``jaw_turns``
        (``vgq.turns``; the camera rolled further by its angle, on a canvas that holds the whole
        image), cached beside it as ``key`` + ``.t<turn>`` with windows on the training grid;
        turn 0 is ``entry`` itself."""
        if turn == 0:
            return key, entry
        key_t = f"{key}.t{turn}"
        turned = self.cache.get(key_t)
        if turned is None:
            depth, canvas, roll = turned_view(entry.depth, entry.resampled, turn, self.model.geometry.jaw_turns)
            turned = CachedImage(
                depth, entry.camera, canvas, entry.assumed, None, entry.up, entry.roll + roll, entry.up_from
            )
            self.cache.put(key_t, turned)
        return key_t, turned

    def _turned_jobs(self, key: str, entry: CachedImage, grasps: np.ndarray, placed: tuple) -> list[tuple]:
        """(key, entry, grasp indices, placement) per turn the grasps ``placed`` in ``entry`` (its
        level frame) fall in, by their in-image jaw angles there (``vgq.turns``)."""
        mapped = placed[2]
        angle = pose_jaw_angles(mapped[:, :2], mapped[:, 2], mapped[:, 3:7], entry.resampled)
        index = turn_index(angle, self.model.geometry.jaw_turns)
        jobs = []
        for t in np.unique(index).tolist():
            ix = np.flatnonzero(index == t)
            if t == 0:
                jobs.append((key, entry, ix, tuple(a[ix] for a in placed)))
                continue
            key_t, turned = self.turned_entry(key, entry, t)
            with _client_rows(ix):
                jobs.append((key_t, turned, ix, self.place(turned, np.asarray(grasps, np.float64)[ix])))
        return jobs

    # ---- answers -------------------------------------------------------------------------------
    def camera_info(self, entry: CachedImage) -> dict:
        c, r = entry.camera, entry.resampled
        return {
            "intrinsics": {k: getattr(c, k) for k in ("fx", "fy", "cx", "cy")},
            "intrinsics_assumed": list(entry.assumed),
            "resampled": {
                "image_shape": [r.height, r.width],
                "scale": list(entry.scale),
                "intrinsics": {k: getattr(r, k) for k in ("fx", "fy", "cx", "cy")},
            },
            "level": describe_level(entry.up, entry.roll, entry.up_from),
        }

    def grasp_range(self, entry: CachedImage) -> dict:
        """Client pixels (u, v ranges) where grasps of a fixed-window upload may lie: the window's
        training range, mapped back (its bounding box when the image was turned level)."""
        k = self.model.geometry.kappa_px
        c = entry.fixed_center
        square = np.array([[c[0] - k, c[1] - k], [c[0] + k, c[1] - k], [c[0] - k, c[1] + k], [c[0] + k, c[1] + k]])
        q = map_pixels(square, entry.resampled, entry.camera, -entry.roll)
        lo, hi = q.min(axis=0), q.max(axis=0)
        return {"u": [float(lo[0]), float(hi[0])], "v": [float(lo[1]), float(hi[1])]}

    def image_info(self, key: str, entry: CachedImage, cached: bool) -> dict:
        out = {
            "image_id": key,
            "cached": cached,
            "model_version": self.model.version,
            "image_shape": list(entry.image_shape),
            "missing_fraction": entry.missing_fraction,
            **self.camera_info(entry),
        }
        if self.placement:
            out["placement"] = image_placement.describe(entry.placement)
        if entry.fixed_center is None:
            out["windows"] = "grid"
            return out
        c = map_pixels(entry.fixed_center[None], entry.resampled, entry.camera, -entry.roll)[0]
        out.update(windows="fixed", window_center=[float(c[0]), float(c[1])], grasp_range=self.grasp_range(entry))
        return out

    def scores_info(self, s: Scores) -> dict:
        out = {
            "p_success": s.p_success,
            "raw_score": s.raw_score,
            "calibrated": self.calibration is not None,
            "ood": s.ood(),
            "ood_mask": s.ood_mask,
            "windows": s.windows,
            "windows_encoded": s.windows_encoded,
            "missing_fraction": s.missing_fraction,
        }
        if s.placement_known is not None:
            out["placement"] = {"table_found": s.table_found, "known": s.placement_known}
        return out


def make_cache(settings: Settings, log: logging.Logger):
    if settings.cache_backend == "redis":
        from .redis_cache import RedisCache

        return RedisCache(
            settings.redis_url, settings.cache_entries, settings.cache_bytes, log, ttl_s=settings.cache_ttl_s
        )
    return MemoryCache(settings.cache_entries, settings.cache_bytes)
