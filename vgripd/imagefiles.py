"""Image files on disk: which files are images, their natural order, and stereo pairing.

Used by the replay camera driver (``drivers.cameras.replay``), ``vgripd replay`` and the
calibration commands, so that all of them read a folder the same way. Pairing rules: see
``list_frames`` and docs/cameras.md.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from vgripd.errors import CameraError

_DIGITS = re.compile(r"(\d+)")


def natural_key(path: str | Path) -> tuple[tuple[int, int | str], ...]:
    """Sort key that orders embedded numbers by value: ``img_2`` < ``img_10`` (the whole path,
    so files of one folder sort by name and folders stay together)."""
    return tuple(
        (0, int(part)) if part.isdigit() else (1, part)
        for part in _DIGITS.split(str(path))
        if part
    )


#: Suffixes of files that ``cv2.imread`` decodes (lower case); anything else is skipped.
IMAGE_SUFFIXES = frozenset({
    ".png", ".jpg", ".jpeg", ".jpe", ".jp2", ".tif", ".tiff", ".bmp", ".dib", ".webp",
    ".pbm", ".pgm", ".ppm", ".pxm", ".pnm", ".pfm", ".sr", ".ras", ".exr", ".hdr", ".pic",
})


def is_image_file(path: Path) -> bool:
    """True for a file whose suffix is an image format OpenCV reads."""
    return path.suffix.lower() in IMAGE_SUFFIXES


@dataclass(frozen=True)
class Frames:
    """The files of a replay, in frame order.

    ``left[i]`` (and ``right[i]`` for stereo) is frame i; ``paired_by`` is "name" (same
    wildcard key), "position" (sorted order) or "single"; ``skipped`` are files a pattern
    matched that are not images.
    """

    folder: Path
    left: list[Path]
    right: list[Path] | None
    paired_by: str
    skipped: list[Path] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.left)


def _pattern_regex(pattern: str) -> re.Pattern[str]:
    """A regex for a glob pattern (relative posix path) with one group per wildcard."""
    out, i = [], 0
    while i < len(pattern):
        c = pattern[i]
        if pattern.startswith("**/", i):
            out.append("((?:.*/)?)")
            i += 3
        elif pattern.startswith("**", i):
            out.append("(.*)")
            i += 2
        elif c == "*":
            out.append("([^/]*)")
            i += 1
        elif c == "?":
            out.append("([^/])")
            i += 1
        elif c == "[" and "]" in pattern[i + 2:]:
            end = pattern.index("]", i + 2)
            body = pattern[i + 1:end]
            if body.startswith("!"):
                body = "^" + body[1:]
            out.append("([" + body.replace("\\", "\\\\") + "])")
            i = end + 1
        else:
            out.append(re.escape(c))
            i += 1
    return re.compile("".join(out))


def _keys(folder: Path, pattern: str, files: list[Path]) -> list[tuple[str, ...]] | None:
    """The wildcard parts of each file's name under ``pattern``; None when one cannot be
    worked out (then pairing falls back to sorted position)."""
    regex = _pattern_regex(pattern)
    keys = []
    for p in files:
        m = regex.fullmatch(p.relative_to(folder).as_posix())
        if m is None:
            return None
        keys.append(m.groups())
    return keys


def _names(paths: list[Path], most: int = 3) -> str:
    text = ", ".join(p.name for p in paths[:most])
    return text + (f" and {len(paths) - most} more" if len(paths) > most else "")


def list_images(folder: Path, pattern: str) -> tuple[list[Path], list[Path]]:
    """Image files matching ``pattern`` in ``folder`` (natural order) and the non-image files
    it also matched."""
    matched = sorted((p for p in folder.glob(pattern) if p.is_file()), key=natural_key)
    images = [p for p in matched if is_image_file(p)]
    return images, [p for p in matched if not is_image_file(p)]


def list_frames(folder: Path, *, glob: str | None = None, left_glob: str | None = None,
                right_glob: str | None = None) -> Frames:
    """The frames of a replay folder: ``glob`` (single camera) or ``left_glob`` + ``right_glob``
    (stereo), paired as the module docstring says. Raises CameraError naming the folder and
    the patterns when there is no image, no right image for a stereo layout, or a file
    without a partner."""
    if (glob is None) == (left_glob is None or right_glob is None):
        raise CameraError("replay: give either glob (single camera) or left_glob and right_glob")
    if not folder.is_dir():
        raise CameraError(f"replay: folder {folder} does not exist")

    def none_match(pattern: str, skipped: list[Path], what: str = "") -> CameraError:
        extra = f" (skipped non-image files: {_names(skipped)})" if skipped else ""
        return CameraError(f"replay: no image files match {what}{pattern!r} in {folder}{extra}")

    if glob is not None:
        images, skipped = list_images(folder, glob)
        if not images:
            raise none_match(glob, skipped)
        return Frames(folder, images, None, "single", skipped)
    assert left_glob is not None
    assert right_glob is not None
    left, skip_l = list_images(folder, left_glob)
    right, skip_r = list_images(folder, right_glob)
    skipped = sorted(set(skip_l) | set(skip_r), key=natural_key)
    if not left:
        raise none_match(left_glob, skipped, "left_glob ")
    if not right:
        raise CameraError(
            f"replay: stereo layout but no image files match right_glob {right_glob!r} in "
            f"{folder} ({len(left)} match left_glob {left_glob!r}): no pairs to replay")
    counts = (f"{len(left)} left images ({left_glob}) but {len(right)} right images "
              f"({right_glob}) in {folder}")
    keys_l, keys_r = _keys(folder, left_glob, left), _keys(folder, right_glob, right)
    if (keys_l is not None and keys_r is not None and len(set(keys_l)) == len(keys_l)
            and len(set(keys_r)) == len(keys_r) and set(keys_l) & set(keys_r)):
        by_key = dict(zip(keys_r, right, strict=True))
        lonely_l = [p for p, k in zip(left, keys_l, strict=True) if k not in by_key]
        lonely_r = [p for p, k in zip(right, keys_r, strict=True) if k not in set(keys_l)]
        if lonely_l or lonely_r:
            why = "; ".join(
                [f"no right image for {_names(lonely_l)}"] * bool(lonely_l)
                + [f"no left image for {_names(lonely_r)}"] * bool(lonely_r))
            if len(left) != len(right):
                raise CameraError(f"replay: {counts}: {why}")
            raise CameraError(f"replay: unpaired files in {folder} (left_glob {left_glob!r}, "
                              f"right_glob {right_glob!r}): {why}")
        return Frames(folder, left, [by_key[k] for k in keys_l], "name", skipped)
    if len(left) != len(right):
        raise CameraError(f"replay: {counts} (paired by sorted position: their names share "
                          "no wildcard part)")
    return Frames(folder, left, right, "position", skipped)


def list_views(folder: Path, globs: Sequence[str]) -> list[list[Path]]:
    """The files of a multi-camera replay: per camera (one pattern each, camera order), its
    files in frame order. Every pattern pairs with the first as a stereo pair would
    (:func:`list_frames`: same wildcard key, else sorted position), so all cameras get the
    same frames or the error names the pattern that does not."""
    if len(globs) < 2:
        raise CameraError(f"replay: globs needs one pattern per camera, got {list(globs)}")
    views: list[list[Path]] = []
    for j, pattern in enumerate(globs[1:], start=1):
        frames = list_frames(folder, left_glob=globs[0], right_glob=pattern)
        assert frames.right is not None
        if views and frames.left != views[0]:
            raise CameraError(f"replay: globs.{j} {pattern!r} pairs with other frames of "
                              f"globs.0 {globs[0]!r} than globs.1 does in {folder}")
        if not views:
            views.append(frames.left)
        views.append(frames.right)
    return views
