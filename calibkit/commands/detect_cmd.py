"""`calibkit detect` and `calibkit mask`: find markers in images and tune the detector."""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from calibkit.clitools import Progress, print_table, write_json
from calibkit.core.errors import UserError
from calibkit.core.fileio import write_bytes_atomic

if TYPE_CHECKING:
    import numpy as np

    from calibkit.cameras import Frame, FrameSource
    from calibkit.vision.detect import Blobs


def parse_threshold(text: str) -> float | str:
    """'auto' or a non-negative pixel value."""
    import numpy as np

    t = text.strip().lower()
    if t == "auto":
        return "auto"
    try:
        value = float(t)
    except ValueError:
        value = float("nan")
    if not np.isfinite(value) or value < 0:
        raise UserError(f"--threshold must be 'auto' or a pixel value >= 0, got {text!r}")
    return value


def parse_hsv(text: str) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
    """'H1,S1,V1:H2,S2,V2' -> ((h, s, v) low, (h, s, v) high)."""
    try:
        lo, hi = text.split(":")
        low = tuple(int(c) for c in lo.split(","))
        high = tuple(int(c) for c in hi.split(","))
        if len(low) != 3 or len(high) != 3:
            raise ValueError
    except ValueError:
        raise UserError(f"--hsv takes H1,S1,V1:H2,S2,V2 (OpenCV HSV, H 0..179), got "
                        f"{text!r}") from None
    return low, high  # type: ignore[return-value]


def annotate(image: np.ndarray, blobs: Blobs, mask: np.ndarray | None = None,
             threshold: float | None = None) -> np.ndarray:
    """A BGR picture for tuning: pixels above the threshold tinted red, masked pixels blue,
    each blob's box in green with a cross at its centroid and its index."""
    import cv2
    import numpy as np

    img = np.asarray(image)
    if img.dtype != np.uint8:
        img = cv2.convertScaleAbs(img, alpha=255.0 / max(float(img.max()), 1.0))
    bgr = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img[:, :, :3].copy()
    gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    if threshold is not None and np.isfinite(threshold):
        above = np.asarray(image) > threshold
        if above.ndim == 3:
            above = gray > threshold
        bgr[above] = (0.5 * bgr[above] + [0, 0, 127]).astype(np.uint8)
    if mask is not None:
        bgr[mask] = (0.5 * bgr[mask] + [110, 0, 0]).astype(np.uint8)
    shift = 4  # sub-pixel drawing: coordinates in 1/16 px
    scale = 1 << shift
    for i, ((u, v), box) in enumerate(zip(blobs.uv, blobs.bbox, strict=True)):
        x0, y0, x1, y1 = (int(b) for b in box)
        cv2.rectangle(bgr, (x0 - 1, y0 - 1), (x1 + 1, y1 + 1), (0, 200, 0), 1)
        cu, cv_ = round(u * scale), round(v * scale)
        arm = 3 * scale
        cv2.line(bgr, (cu - arm, cv_), (cu + arm, cv_), (0, 255, 255), 1, cv2.LINE_AA, shift)
        cv2.line(bgr, (cu, cv_ - arm), (cu, cv_ + arm), (0, 255, 255), 1, cv2.LINE_AA, shift)
        cv2.putText(bgr, str(i), (x1 + 3, y0 + 4), cv2.FONT_HERSHEY_PLAIN, 0.8, (0, 220, 0))
    return bgr


def _write_png(path: Path, image: np.ndarray) -> None:
    import cv2

    ok, data = cv2.imencode(".png", image)
    if not ok:  # pragma: no cover
        raise RuntimeError("PNG encoding failed")
    write_bytes_atomic(path, data.tobytes())


def _source(source: str | None, sim: bool, frames: int | None, markers: int, seed: int,
            camera: str, reflections: int = 0) -> tuple[FrameSource, int | None]:
    from calibkit.cameras import SPEC_HELP, open_camera
    from calibkit.synthetic.frames import sim_source

    if sim:
        cam: int | str = int(camera) if camera.isdigit() else camera
        return sim_source(n_markers=markers, n_frames=frames or 1, camera=cam, seed=seed,
                          reflections=reflections), None
    if source is None:
        raise UserError(f"give a SOURCE or --sim: {SPEC_HELP}")
    src = open_camera(source)
    limit = frames
    if limit is None and src.capabilities.live:
        limit = 1  # a live camera: one frame unless told otherwise
    return src, limit


def register(app: typer.Typer) -> None:
    @app.command("detect")
    def detect_command(
        source: Annotated[str | None, typer.Argument(
            help="A camera: an image, a folder of images, a video file, a camera device "
                 "number, basler:SERIAL or genicam:SERIAL.")]
        = None,
        sim: Annotated[bool, typer.Option(
            "--sim", help="Use a simulated camera (and score against its truth).")] = False,
        threshold: Annotated[str, typer.Option(
            help="'auto' (background + noise margin) or a pixel value.")] = "auto",
        min_area: Annotated[float, typer.Option(help="Smallest blob, pixels.")] = 2.0,
        max_area: Annotated[float, typer.Option(help="Largest blob, pixels.")] = 4000.0,
        min_roundness: Annotated[float, typer.Option(
            help="Smallest minor/major axis ratio, 0..1.")] = 0.0,
        multi: Annotated[bool, typer.Option(
            "--multi", help="Multi-threshold mode for touching or unevenly lit markers.")]
        = False,
        hsv: Annotated[list[str] | None, typer.Option(
            help="Colour range H1,S1,V1:H2,S2,V2 (OpenCV HSV, H 0..179); repeat for more.")]
        = None,
        mask: Annotated[Path | None, typer.Option(
            help="PNG of pixels to ignore (white), from `calibkit mask`.")] = None,
        preview: Annotated[Path | None, typer.Option(
            help="Write an annotated PNG of the first frame.")] = None,
        json_path: Annotated[Path | None, typer.Option(
            "--json", help="Write the blobs as JSON.")] = None,
        frames: Annotated[int | None, typer.Option(help="At most this many frames.")] = None,
        markers: Annotated[int, typer.Option(help="--sim: number of markers.")] = 40,
        seed: Annotated[int, typer.Option(help="--sim: random seed.")] = 0,
        camera: Annotated[str, typer.Option(help="--sim: camera index or name.")] = "0",
        reflections: Annotated[int, typer.Option(
            help="--sim: static reflections the camera also sees (the ones `calibkit mask "
                 "--sim` masks for the same --camera and --seed).")] = 0,
    ) -> None:
        """Find markers in images and print them; tune the options with --preview."""
        from calibkit.vision.detect import DetectorConfig, detect
        from calibkit.vision.masks import load_mask

        if frames is not None and frames < 1:
            raise UserError(f"--frames must be >= 1, got {frames}")
        config = DetectorConfig(threshold=parse_threshold(threshold), min_area=min_area,
                                max_area=max_area, min_roundness=min_roundness,
                                mode="multi" if multi else "threshold",
                                hsv_ranges=tuple(parse_hsv(h) for h in hsv or ()))
        ignore = load_mask(mask) if mask is not None else None
        src, limit = _source(source, sim, frames, markers, seed, camera, reflections)
        results: list[tuple[Frame, Blobs]] = []
        progress = Progress("detect", limit)
        with src:
            for frame in itertools.islice(src, limit):
                if ignore is not None and ignore.shape != frame.image.shape[:2]:
                    raise UserError(f"mask {mask} is {ignore.shape[1]}x{ignore.shape[0]} "
                                    f"but the frames are {frame.image.shape[1]}x"
                                    f"{frame.image.shape[0]}")
                cfg = config if ignore is None else config.replace(mask=ignore)
                blobs = detect(frame.image, cfg)
                results.append((frame, blobs))
                if preview is not None and len(results) == 1:
                    _write_png(preview, annotate(frame.image, blobs, ignore, blobs.threshold))
                progress.update(len(results))
        if len(results) > 1:
            progress.finish()
        if not results:
            raise UserError(f"{source} gave no frames")
        _report(results, getattr(src, "truth_uv", None), json_path)

    @app.command("mask")
    def mask_command(
        source: Annotated[str | None, typer.Argument(
            help="Frames with no markers in view from a camera: an image, a folder, a video, "
                 "a camera device number, basler:SERIAL or genicam:SERIAL.")] = None,
        out: Annotated[Path | None, typer.Option(help="The mask PNG to write.")] = None,
        frames: Annotated[int, typer.Option(help="Use at most this many frames.")] = 30,
        dilate: Annotated[int, typer.Option(help="Grow masked areas by this many pixels.")]
        = 4,
        threshold: Annotated[str, typer.Option(help="'auto' or a pixel value.")] = "auto",
        json_path: Annotated[Path | None, typer.Option(
            "--json", help="Write the mask's figures as JSON.")] = None,
        sim: Annotated[bool, typer.Option(
            "--sim", help="Frames of a simulated camera with its markers taken away and "
                          "--reflections static reflections left; the mask is scored "
                          "against where the reflections truly are and where the markers "
                          "of `calibkit detect --sim` image.")] = False,
        reflections: Annotated[int, typer.Option(
            help="--sim: static reflections the camera sees (glints to lamps).")] = 8,
        markers: Annotated[int, typer.Option(
            help="--sim: markers whose images the mask must leave alone (scoring only: "
                 "the frames have none).")] = 40,
        seed: Annotated[int, typer.Option(help="--sim: random seed.")] = 0,
        camera: Annotated[str, typer.Option(help="--sim: camera index or name.")] = "0",
    ) -> None:
        """Build a mask of static reflections and lamps from frames with no markers."""
        import cv2
        import numpy as np

        from calibkit.vision.masks import build_mask, save_mask

        if out is None:
            raise UserError("--out MASK.png is required: where to write the mask")
        if frames < 1:
            raise UserError(f"--frames must be >= 1, got {frames}")
        level = parse_threshold(threshold)
        with _mask_source(source, sim, frames, reflections, seed, camera) as src:
            images = [f.image for f in itertools.islice(src, frames)]
        if not images:
            raise UserError(f"{source} gave no frames")
        result = build_mask(images, threshold=level, dilate_px=dilate)
        save_mask(out, result)
        fraction = float(result.mean())
        n_regions = cv2.connectedComponents(result.view(np.uint8))[0] - 1
        print(f"mask {out}: {result.shape[1]}x{result.shape[0]}, {int(result.sum())} pixels "
              f"({100 * fraction:.2f}%) in {n_regions} areas masked, from {len(images)} "
              f"frames")
        data = {"mask": str(out), "width": result.shape[1], "height": result.shape[0],
                "frames": len(images), "masked_pixels": int(result.sum()),
                "masked_fraction": fraction, "areas": n_regions}
        if sim:
            data["truth"] = _mask_truth(result, reflections, markers, seed, camera)
        if json_path is not None:
            write_json(json_path, data)


def _mask_source(source: str | None, sim: bool, frames: int, reflections: int, seed: int,
                 camera: str) -> FrameSource:
    from calibkit.cameras import SPEC_HELP, open_camera
    from calibkit.synthetic.frames import empty_volume

    if sim:
        if source is not None:
            raise UserError(f"give a SOURCE or --sim, not both (got {source!r} and --sim)")
        return empty_volume(frames, int(camera) if camera.isdigit() else camera, seed,
                            reflections)
    if source is None:
        raise UserError(f"give a SOURCE or --sim: {SPEC_HELP}")
    return open_camera(source)


def _mask_truth(mask: np.ndarray, reflections: int, markers: int, seed: int,
                camera: str) -> dict:
    """--sim: the mask against where the reflections are and where the markers image."""
    from calibkit.synthetic.frames import sim_camera, sim_source
    from calibkit.synthetic.reflections import make_reflections, marker_discs, score_mask

    cam_id: int | str = int(camera) if camera.isdigit() else camera
    cam = sim_camera(cam_id, seed)
    scene = sim_source(n_markers=markers, camera=cam_id, seed=seed)
    uv, radius = marker_discs(cam, scene.xyz[0])
    truth = score_mask(mask, make_reflections(cam, reflections, seed), uv, radius)
    print(f"against the simulator's truth: {truth['reflections_covered']}/"
          f"{truth['reflections']} reflections wholly masked "
          f"({100 * truth['reflection_pixels_covered']:.1f}% of their pixels); "
          f"{truth['markers_touched']}/{truth['markers']} markers' images touched by the "
          f"mask, {truth['markers_hidden']} hidden")
    return truth


def _truth_figures(results: list[tuple[Frame, Blobs]],
                   truth_uv: dict[int, np.ndarray] | None) -> dict | None:
    """Recall, false blobs and centroid error against a simulated source's true centres."""
    import numpy as np

    from calibkit.synthetic.truthcheck import match_to_truth

    if truth_uv is None or any(f.index not in truth_uv for f, _ in results):
        return None
    errors, n_true, n_found, n_false = [], 0, 0, 0
    for frame, blobs in results:
        true_uv = truth_uv[frame.index]
        det, tru = match_to_truth(blobs.uv, true_uv)
        errors.append(blobs.uv[det] - true_uv[tru])
        n_true += len(true_uv)
        n_found += len(det)
        n_false += len(blobs) - len(det)
    err = np.concatenate(errors) if errors else np.zeros((0, 2))
    rms = float(np.sqrt((err ** 2).sum(axis=1).mean())) if len(err) else float("nan")
    return {"markers": n_true, "found": n_found, "recall": n_found / max(n_true, 1),
            "false_blobs": n_false, "centroid_rms_px": rms}


def _report(results: list[tuple[Frame, Blobs]], truth_uv: dict[int, np.ndarray] | None,
            json_path: Path | None) -> None:
    import numpy as np

    truth = _truth_figures(results, truth_uv)
    if len(results) == 1:
        frame, blobs = results[0]
        several = len(set(blobs.label.tolist())) > 1
        rows = [[i, f"{u:9.3f}", f"{v:9.3f}", int(a), int(p), f"{r:5.3f}",
                 *([int(lab)] if several else [])]
                for i, ((u, v), a, p, r, lab) in enumerate(zip(
                    blobs.uv, blobs.area, blobs.peak, blobs.roundness, blobs.label,
                    strict=True))]
        header = ["#", "u", "v", "area", "peak", "roundness"]
        if several:
            header.append("hsv")
        print_table(rows, header)
        level = "" if not np.isfinite(blobs.threshold) else f" (threshold {blobs.threshold:.1f})"
        print(f"{len(blobs)} blobs in {frame.camera}{level}")
        data = {"camera": frame.camera, "threshold": blobs.threshold,
                "blobs": blobs.to_records()}
    else:
        rows = [[f.index, f.t_ns / 1e9, len(b), float(np.nanmean(b.area)) if len(b) else 0.0]
                for f, b in results]
        print_table(rows, ["frame", "t_s", "blobs", "mean_area"])
        total = sum(len(b) for _, b in results)
        print(f"{total} blobs in {len(results)} frames of {results[0][0].camera}")
        data = {"frames": [{"camera": f.camera, "index": f.index, "t_ns": f.t_ns,
                            "threshold": b.threshold, "blobs": b.to_records()}
                           for f, b in results]}
    if truth is not None:
        print(f"against the simulator's truth: recall {100 * truth['recall']:.1f}% "
              f"({truth['found']}/{truth['markers']}), {truth['false_blobs']} false blobs, "
              f"centroid error {truth['centroid_rms_px']:.3f} px RMS")
        data["truth"] = truth
    if json_path is not None:
        write_json(json_path, data)
