"""Depth maps that phones embed in their photos.

Three containers are understood:

* Google Camera "Lens Blur" JPEG: XMP ``GDepth:Data`` (base64 PNG/JPEG depth, ``Format``
  RangeInverse or RangeLinear with ``Near``/``Far``), ``GImage:Data`` (the original
  all-in-focus photo; the main JPEG is Google's blurred rendering) and ``GFocus`` (focal
  distance and focal point). The large properties live in *extended XMP*: several APP1
  segments tagged ``http://ns.adobe.com/xmp/extension/``, each carrying a 32-byte GUID, the
  total length and its own offset. The JPEG segments are parsed here directly.
* Apple portrait JPEG (MPO): frame 1 is an 8-bit disparity map described by ``apdi`` XMP
  (``FloatMinValue``/``FloatMaxValue``); a later frame may hold a portrait matte. The
  photo's ``mwg-rs`` Focus/Face region gives the focus point.
* Apple HEIC: the auxiliary depth image that pillow-heif exposes, with its ``d_min``/``d_max``
  and ``representation_type`` metadata.

All maps are returned as normalised disparity (HxW float32 in [0, 1], 1 = nearest) at the
photo's upright resolution, with the focal plane as a disparity in the same scale.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import logging
import re
import struct
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from PIL import Image

from .depth import normalize_disparity
from .formats import apply_orientation, exif_orientation
from .image import (
    ImageInfo,
    ImageSource,
    decode_image,
    ensure_heif_support,
    is_heif,
    open_pil,
    read_source_bytes,
    resize_float,
    source_name,
)

logger = logging.getLogger(__name__)

XMP_STD_SIG = b"http://ns.adobe.com/xap/1.0/\x00"
XMP_EXT_SIG = b"http://ns.adobe.com/xmp/extension/\x00"

NS_GDEPTH = "http://ns.google.com/photos/1.0/depthmap/"
NS_GIMAGE = "http://ns.google.com/photos/1.0/image/"
NS_GFOCUS = "http://ns.google.com/photos/1.0/focus/"
NS_XMPNOTE = "http://ns.adobe.com/xmp/note/"
NS_APDI = "http://ns.apple.com/pixeldatainfo/1.0/"
NS_DEPTHBLUR = "http://ns.apple.com/depthBlurEffect/1.0/"
NS_MWG_RS = "http://www.metadataworkinggroup.com/schemas/regions/"
NS_ST_AREA = "http://ns.adobe.com/xmp/sType/Area#"
NS_RDF = "http://www.w3.org/1999/02/22-rdf-syntax-ns#"


# --------------------------------------------------------------------------- JPEG segments


def jpeg_segments(data: bytes) -> list[tuple[int, bytes]]:
    """Marker segments of a JPEG before its image data: ``[(marker, payload), ...]``.

    Stops at start-of-scan; a truncated segment ends the list (the image decoder reports
    truncation itself).
    """
    if not data.startswith(b"\xff\xd8"):
        raise ValueError("not a JPEG file (no SOI marker)")
    segments: list[tuple[int, bytes]] = []
    pos = 2
    n = len(data)
    while pos < n:
        if data[pos] != 0xFF:
            logger.debug("JPEG marker expected at byte %d; stopping the segment scan", pos)
            break
        while pos < n and data[pos] == 0xFF:  # fill bytes
            pos += 1
        if pos >= n:
            break
        marker = data[pos]
        pos += 1
        if marker in (0x01, 0xD8) or 0xD0 <= marker <= 0xD7:
            continue  # markers without a length field
        if marker in (0xD9, 0xDA):
            break
        if pos + 2 > n:
            break
        (length,) = struct.unpack(">H", data[pos : pos + 2])
        if length < 2 or pos + length > n:
            break
        segments.append((marker, data[pos + 2 : pos + length]))
        pos += length
    return segments


def extract_xmp(data: bytes) -> tuple[bytes | None, bytes | None]:
    """Standard and (reassembled) extended XMP packets of a JPEG.

    Extended XMP chunks are grouped by GUID and placed at their offsets; the GUID named by
    ``xmpNote:HasExtendedXMP`` in the standard packet wins when several are present.
    """
    standard = None
    chunks: dict[bytes, dict] = {}
    for marker, payload in jpeg_segments(data):
        if marker != 0xE1:
            continue
        if payload.startswith(XMP_STD_SIG) and standard is None:
            standard = payload[len(XMP_STD_SIG) :]
        elif payload.startswith(XMP_EXT_SIG):
            body = payload[len(XMP_EXT_SIG) :]
            if len(body) < 40:
                continue
            guid = body[:32]
            total, offset = struct.unpack(">II", body[32:40])
            entry = chunks.setdefault(guid, {"total": total, "parts": []})
            entry["parts"].append((offset, body[40:]))
    if not chunks:
        return standard, None
    wanted = None
    if standard is not None:
        m = re.search(rb"HasExtendedXMP\s*(?:=\s*[\"']|>)\s*([0-9A-Fa-f]{32})", standard)
        if m:
            wanted = m.group(1).upper()
    guid = next((g for g in chunks if g.upper() == wanted), None) or next(iter(chunks))
    entry = chunks[guid]
    present = sum(len(part) for _, part in entry["parts"])
    if entry["total"] > present:  # before the buffer: the total is only what the file says
        raise ValueError(f"extended XMP is incomplete: {present} of {entry['total']} bytes present")
    buf = bytearray(entry["total"])
    covered = 0
    for offset, part in sorted(entry["parts"]):
        end = min(offset + len(part), len(buf))
        buf[offset:end] = part[: end - offset]
        covered += end - offset
    if covered < entry["total"]:
        raise ValueError(f"extended XMP is incomplete: {covered} of {entry['total']} bytes present")
    if hashlib.md5(bytes(buf)).hexdigest().upper().encode() != guid.upper():
        logger.debug("extended XMP GUID does not match the MD5 of its content")
    return standard, bytes(buf)


# --------------------------------------------------------------------------- XMP parsing


def _parse_xml(packet: bytes) -> ET.Element | None:
    text = packet.strip(b"\x00 \t\r\n")
    start = text.find(b"<x:xmpmeta")
    if start < 0:
        start = text.find(b"<rdf:RDF")
    if start < 0:
        return None
    end_tag = b"</x:xmpmeta>" if text[start:].startswith(b"<x:xmpmeta") else b"</rdf:RDF>"
    end = text.rfind(end_tag)
    if end < 0:
        return None
    try:
        return ET.fromstring(text[start : end + len(end_tag)])
    except ET.ParseError as exc:
        logger.warning("unparsable XMP packet: %s", exc)
        return None


def _split(tag: str) -> tuple[str, str]:
    if tag.startswith("{"):
        ns, _, local = tag[1:].partition("}")
        return ns, local
    return "", tag


def xmp_properties(*packets: bytes | None) -> dict[tuple[str, str], str]:
    """Simple XMP properties keyed by (namespace URI, local name), from attributes and from
    leaf elements. The first occurrence of a key wins."""
    props: dict[tuple[str, str], str] = {}
    for packet in packets:
        if not packet:
            continue
        root = _parse_xml(packet)
        if root is None:
            continue
        for el in root.iter():
            for key, value in el.attrib.items():
                props.setdefault(_split(key), value)
            if len(el) == 0 and el.text and el.text.strip():
                props.setdefault(_split(el.tag), el.text.strip())
    return props


def xmp_regions(packet: bytes | None) -> list[dict[str, Any]]:
    """MWG regions (``mwg-rs:RegionList``) as dicts with type and x, y (centre), w, h in
    normalised image coordinates."""
    root = _parse_xml(packet) if packet else None
    if root is None:
        return []
    regions = []
    for li in root.iter(f"{{{NS_RDF}}}li"):
        rtype = li.find(f"{{{NS_MWG_RS}}}Type")
        area = li.find(f"{{{NS_MWG_RS}}}Area")
        if rtype is None or area is None:
            continue
        vals: dict[str, Any] = {"type": (rtype.text or "").strip()}
        for key in ("x", "y", "w", "h"):
            el = area.find(f"{{{NS_ST_AREA}}}{key}")
            raw = el.text if el is not None else area.attrib.get(f"{{{NS_ST_AREA}}}{key}")
            try:
                vals[key] = float(raw)  # type: ignore[arg-type]
            except (TypeError, ValueError):
                vals[key] = None
        if vals["x"] is not None and vals["y"] is not None:
            regions.append(vals)
    return regions


def _float(props: dict, ns: str, key: str) -> float | None:
    value = props.get((ns, key))
    if value is None:
        return None
    try:
        out = float(value)
    except ValueError:
        return None
    return out if np.isfinite(out) else None


# --------------------------------------------------------------------------- helpers


def _grey_unit(im: Image.Image) -> np.ndarray:
    """Single-channel map of a decoded image as float64 in [0, 1] (by its bit depth)."""
    if im.mode.startswith("I;16"):
        return np.asarray(im).astype(np.float64) / 65535.0
    if im.mode == "I":
        a = np.asarray(im).astype(np.float64)
        return a / (65535.0 if a.max() <= 65535 else a.max())
    if im.mode == "F":
        return np.asarray(im).astype(np.float64)
    if im.mode not in ("L", "LA", "RGB", "RGBA", "P"):
        im = im.convert("L")
    a = np.asarray(im.convert("L") if im.mode == "P" else im).astype(np.float64) / 255.0
    return a[..., 0] if a.ndim == 3 else a


def _focus_from_point(disp: np.ndarray, x: float, y: float, frac: float = 0.02) -> float:
    """Median disparity in a small window around a point given as image fractions."""
    h, w = disp.shape
    cx = int(np.clip(round(x * (w - 1)), 0, w - 1))
    cy = int(np.clip(round(y * (h - 1)), 0, h - 1))
    r = max(1, int(round(frac * max(h, w))))
    win = disp[max(0, cy - r) : cy + r + 1, max(0, cx - r) : cx + r + 1]
    return float(np.median(win))


def _focus_from_region(disp: np.ndarray, region: dict[str, Any]) -> float:
    h, w = disp.shape
    rw = region.get("w") or 0.0
    rh = region.get("h") or 0.0
    x0 = int(np.clip((region["x"] - rw / 2) * w, 0, w - 1))
    x1 = int(np.clip((region["x"] + rw / 2) * w, x0 + 1, w))
    y0 = int(np.clip((region["y"] - rh / 2) * h, 0, h - 1))
    y1 = int(np.clip((region["y"] + rh / 2) * h, y0 + 1, h))
    if (x1 - x0) * (y1 - y0) < 4:
        return _focus_from_point(disp, region["x"], region["y"])
    return float(np.median(disp[y0:y1, x0:x1]))


def _upright_size(im: Image.Image) -> tuple[int, int]:
    w, h = im.size
    return (h, w) if exif_orientation(im) < 5 else (w, h)


def _finish(disp: np.ndarray, orientation: int, size: tuple[int, int], name: str) -> np.ndarray:
    """Orient like the photo, check the aspect ratio and resize to ``size``."""
    disp = apply_orientation(disp, orientation)
    h, w = disp.shape
    if abs(np.log((w / h) / (size[1] / size[0]))) > 0.05:
        raise ValueError(
            f"{name}: embedded depth map is {w}x{h} but the photo is {size[1]}x{size[0]}"
        )
    out = resize_float(disp.astype(np.float32), size, "bilinear")
    return np.clip(out, 0.0, 1.0).astype(np.float32)


# --------------------------------------------------------------------------- Google


def _check_depth_size(size: tuple[int, int], max_pixels: int, what: str) -> None:
    """Refuse an embedded depth image larger than the photo, from its header (before Pillow
    allocates it): a phone's depth map is never larger than its photo."""
    w, h = size
    if w * h > max_pixels:
        raise ValueError(
            f"{what}: the depth image claims {w}x{h} pixels, more than the photo's {max_pixels}"
        )


def _read_google(
    data: bytes, name: str, size: tuple[int, int] | None, orientation: int, max_pixels: int
):
    try:
        standard, extended = extract_xmp(data)
    except ValueError as exc:
        raise ValueError(f"{name}: {exc}") from exc
    props = xmp_properties(standard, extended)
    depth_b64 = props.get((NS_GDEPTH, "Data"))
    if not depth_b64:
        return None
    try:
        depth_bytes = base64.b64decode(re.sub(r"\s+", "", depth_b64), validate=True)
    except (binascii.Error, ValueError) as exc:
        raise ValueError(f"{name}: GDepth:Data is not valid base64: {exc}") from exc
    dim = open_pil(depth_bytes, f"{name} (GDepth:Data)")
    _check_depth_size(dim.size, max_pixels, f"{name}: GDepth:Data")
    try:
        dim.load()
        v = np.clip(_grey_unit(dim), 0.0, 1.0)
    except (OSError, SyntaxError, ValueError) as exc:
        raise ValueError(f"{name}: GDepth:Data image is corrupt: {exc}") from exc
    fmt = props.get((NS_GDEPTH, "Format"), "RangeInverse")
    near = _float(props, NS_GDEPTH, "Near")
    far = _float(props, NS_GDEPTH, "Far")
    info: dict[str, Any] = {
        "source": "google_gdepth",
        "format": fmt,
        "near": near,
        "far": far,
        "units": props.get((NS_GDEPTH, "Units")),
        "native_size": v.shape,
        "kind": "depth",
    }
    if near is not None and far is not None and far > near > 0:
        if fmt == "RangeLinear":
            z = near + v * (far - near)
        else:
            if fmt != "RangeInverse":
                logger.warning("%s: unknown GDepth:Format %r, read as RangeInverse", name, fmt)
            z = far * near / (far - v * (far - near))
        inv = 1.0 / z
        lo, hi = float(inv.min()), float(inv.max())
        disp = (inv - lo) / (hi - lo) if hi > lo else np.full_like(inv, 0.5)
    else:
        # Without the range only the order is known: both formats store near as 0.
        logger.warning("%s: GDepth Near/Far missing; using the map's inverted values", name)
        lo = hi = None
        disp = normalize_disparity(1.0 - v, robust=False).astype(np.float64)

    focus = None
    fx = _float(props, NS_GFOCUS, "FocalPointX")
    fy = _float(props, NS_GFOCUS, "FocalPointY")
    fdist = _float(props, NS_GFOCUS, "FocalDistance")
    if fdist is not None and fdist > 0 and lo is not None and hi > lo:
        focus = float(np.clip((1.0 / fdist - lo) / (hi - lo), 0.0, 1.0))
    elif fx is not None and fy is not None:
        focus = _focus_from_point(disp, fx, fy)
    info.update(
        focus=focus,
        focus_point=(fx, fy) if fx is not None and fy is not None else None,
        focal_distance=fdist,
        blur_at_infinity=_float(props, NS_GFOCUS, "BlurAtInfinity"),
    )
    image_b64 = props.get((NS_GIMAGE, "Data"))
    if image_b64:
        try:
            info["original_image"] = base64.b64decode(re.sub(r"\s+", "", image_b64))
            info["original_mime"] = props.get((NS_GIMAGE, "Mime"), "image/jpeg")
        except (binascii.Error, ValueError):
            logger.warning("%s: GImage:Data is not valid base64; ignored", name)
    if size is None:
        size = (v.shape[0], v.shape[1]) if orientation < 5 else (v.shape[1], v.shape[0])
    return _finish(disp, orientation, size, name), info


# --------------------------------------------------------------------------- Apple MPO


#: What Pillow raises on a cut or damaged MPO frame: a frame cut inside its markers ends in
#: ``struct.error`` or ``IndexError`` from the JPEG header parser, not in ``OSError``.
_CORRUPT_FRAME = (OSError, SyntaxError, EOFError, ValueError, struct.error, IndexError)


def _read_apple_mpo(im: Image.Image, name: str, size: tuple[int, int], orientation: int):
    n_frames = getattr(im, "n_frames", 1)
    if im.format != "MPO" or n_frames < 2:
        return None
    max_pixels = im.size[0] * im.size[1]
    primary_xmp = im.info.get("xmp")
    depth = None
    props_depth: dict = {}
    matte = None
    for index in range(1, n_frames):
        try:
            im.seek(index)
            _check_depth_size(im.size, max_pixels, f"{name}: MPO frame {index}")
            props = xmp_properties(im.info.get("xmp"))
            aux = props.get((NS_APDI, "AuxiliaryImageType"))
            sub = props.get((NS_APDI, "AuxiliaryImageSubType"))
            if aux is None:
                continue
            im.load()
            if sub:
                if "matte" in sub.lower() and matte is None:
                    matte = np.clip(_grey_unit(im), 0.0, 1.0).astype(np.float32)
                continue
            if aux in ("disparity", "depth") and depth is None:
                depth = _grey_unit(im)
                props_depth = props
                props_depth["frame"] = str(index)
        except _CORRUPT_FRAME as exc:
            raise ValueError(f"{name}: MPO auxiliary frame {index} is corrupt: {exc}") from exc
    try:
        im.seek(0)
    except _CORRUPT_FRAME as exc:
        raise ValueError(f"{name}: MPO primary frame is corrupt: {exc}") from exc
    if depth is None:
        return None
    aux = props_depth[(NS_APDI, "AuxiliaryImageType")]
    fmin = _float(props_depth, NS_APDI, "FloatMinValue")
    fmax = _float(props_depth, NS_APDI, "FloatMaxValue")
    imin = _float(props_depth, NS_APDI, "IntMinValue") or 0.0
    imax = _float(props_depth, NS_APDI, "IntMaxValue") or 255.0
    v = np.clip((depth * 255.0 - imin) / max(imax - imin, 1e-9), 0.0, 1.0)
    if fmin is not None and fmax is not None:
        value = fmin + v * (fmax - fmin)
    else:
        value = v
    if aux == "depth":
        value = 1.0 / np.maximum(value, 1e-6)
    disp = normalize_disparity(value, robust=False).astype(np.float64)
    info: dict[str, Any] = {
        "source": "apple_mpo",
        "kind": aux,
        "frame": int(props_depth["frame"]),
        "float_range": (fmin, fmax),
        "native_size": depth.shape,
        "simulated_aperture": _float(props_depth, NS_DEPTHBLUR, "SimulatedAperture"),
    }
    if matte is not None:
        info["matte"] = matte
    _add_region_focus(info, disp, primary_xmp, orientation)
    return _finish(disp, orientation, size, name), info


def _add_region_focus(info: dict, disp: np.ndarray, xmp: bytes | None, orientation: int):
    """Focus from the photo's MWG Focus (else Face) region. Regions are given in the
    stored (unrotated) frame, like the depth map before orientation."""
    regions = xmp_regions(xmp)
    chosen = next((r for r in regions if r["type"].lower() == "focus"), None)
    chosen = chosen or next((r for r in regions if r["type"].lower() == "face"), None)
    info["focus"] = None
    info["focus_point"] = None
    if chosen is not None:
        info["focus"] = _focus_from_region(disp, chosen)
        point = np.zeros(disp.shape, bool)
        h, w = disp.shape
        point[int(np.clip(chosen["y"] * h, 0, h - 1)), int(np.clip(chosen["x"] * w, 0, w - 1))] = (
            True
        )
        ys, xs = np.nonzero(apply_orientation(point, orientation))
        uh, uw = (h, w) if orientation < 5 else (w, h)
        info["focus_point"] = (float(xs[0] / max(uw - 1, 1)), float(ys[0] / max(uh - 1, 1)))
        info["focus_region"] = chosen


# --------------------------------------------------------------------------- Apple HEIC


def _read_heic(data: bytes, name: str, size: tuple[int, int] | None):
    ensure_heif_support(name)
    im = open_pil(data, name)
    with im:
        depth_images = im.info.get("depth_images") or []
        if not depth_images:
            return None
        if size is None:
            size = _upright_size(im)
        xmp = im.info.get("xmp")
        dimg = depth_images[0]
        meta = dict(dimg.info.get("metadata") or {})
        try:
            d = dimg.to_pillow()
            v = np.clip(_grey_unit(d), 0.0, 1.0)
        except Exception as exc:  # pillow-heif raises its own error types
            raise ValueError(f"{name}: HEIC depth image cannot be decoded: {exc}") from exc
    rep = meta.get("representation_type")
    d_min, d_max = meta.get("d_min"), meta.get("d_max")
    # ISO/IEC 23002-3 representation types: 0 uniform inverse Z, 1 uniform disparity,
    # 2 uniform Z, 3 non-uniform disparity. Only uniform Z stores distance directly.
    if rep == 2:
        lo = d_min if d_min and d_min > 0 else 1.0
        hi = d_max if d_max and d_max > lo else lo + 1.0
        value = 1.0 / (lo + v * (hi - lo))
        kind = "depth"
    else:
        value = v
        kind = "disparity"
    disp = normalize_disparity(value, robust=False).astype(np.float64)
    info: dict[str, Any] = {
        "source": "apple_heic",
        "kind": kind,
        "representation_type": rep,
        "d_min": d_min,
        "d_max": d_max,
        "native_size": v.shape,
    }
    # pillow-heif already applied the container's rotation to both images.
    _add_region_focus(info, disp, xmp, 1)
    return _finish(disp, 1, size, name), info


# --------------------------------------------------------------------------- public


def read_embedded_depth(
    src: ImageSource, *, size: tuple[int, int] | None = None
) -> tuple[np.ndarray, dict[str, Any]] | None:
    """Find a phone depth map inside a photo.

    Args:
        src: path or bytes of a JPEG (Google Lens Blur, Apple portrait MPO) or HEIC.
        size: (H, W) of the result; default the photo's upright size.

    Returns:
        None when the photo carries no depth; else ``(disparity, info)``: disparity is HxW
        float32 in [0, 1], 1 = nearest, oriented like the upright photo. ``info`` holds
        ``source`` (``"google_gdepth"``, ``"apple_mpo"``, ``"apple_heic"``), ``focus``
        (focal-plane disparity in the same [0, 1] scale, or None), ``focus_point``
        ((x, y) as fractions of the upright image, or None), ``native_size`` and
        format-specific fields (``near``/``far``, ``original_image`` bytes for Google's
        all-in-focus photo, ``matte`` for Apple's portrait matte, ...).

    Raises:
        ValueError: the photo declares depth data but it is corrupt.
    """
    name = source_name(src)
    data = read_source_bytes(src)
    if is_heif(data):
        return _read_heic(data, name, size)
    if not data.startswith(b"\xff\xd8"):
        return None
    im = open_pil(data, name)
    with im:
        orientation = exif_orientation(im)
        if size is None:
            size = _upright_size(im)
        found = _read_google(data, name, size, orientation, im.size[0] * im.size[1])
        if found is None:
            found = _read_apple_mpo(im, name, size, orientation)
    return found


@dataclass
class Photo:
    """A photo ready for the pipeline.

    Attributes:
        image: HxWx3 float32 in [0, 1], upright; for a Lens Blur file the embedded original
            (all-in-focus) photo, not Google's blurred rendering.
        info: what the image loader learned and did (ICC, EXIF, conversions).
        disparity: HxW float32 in [0, 1] (1 = nearest) at the image's size, or None.
        focus: focal-plane disparity suggested by the file, or None.
        depth_info: the embedded-depth description (see :func:`read_embedded_depth`),
            without the large byte fields, or None.
    """

    image: np.ndarray
    info: ImageInfo
    disparity: np.ndarray | None = None
    focus: float | None = None
    depth_info: dict[str, Any] | None = None


def load_photo(
    src: ImageSource,
    *,
    max_pixels: int | None = None,
    on_too_large: Literal["resize", "error"] = "resize",
    use_embedded: bool = True,
    min_side: int | None = None,
) -> Photo:
    """Load a photo and, when present, its embedded phone depth and focus.

    A corrupt embedded depth map is logged and ignored (the photo is still usable).
    See :func:`~d2f_core.io.image.load_image_with_info` for the other arguments
    (``min_side`` applies to the photo, checked from its header before decoding).
    """
    name = source_name(src)
    data = read_source_bytes(src)
    image, info = decode_image(
        data, name, max_pixels=max_pixels, on_too_large=on_too_large, min_side=min_side
    )
    photo = Photo(image=image, info=info)
    if not use_embedded:
        return photo
    try:
        found = read_embedded_depth(data if name == "<bytes>" else src, size=info.size)
    except ValueError as exc:
        logger.warning("%s: ignoring embedded depth: %s", name, exc)
        return photo
    if found is None:
        return photo
    disparity, dinfo = found
    original = dinfo.pop("original_image", None)
    if original is not None:
        try:
            orig, orig_info = decode_image(
                original, f"{name} (GImage)", max_pixels=max_pixels, on_too_large="resize"
            )
        except ValueError as exc:
            logger.warning("%s: embedded original photo unusable: %s", name, exc)
        else:
            if orig.shape[:2] != image.shape[:2]:
                orig = resize_float(orig, image.shape[:2])
            photo.image = np.clip(orig, 0.0, 1.0, out=orig)  # in place: no third picture
            info.conversions.append("used the embedded all-in-focus original (GImage:Data)")
            dinfo["used_original_image"] = True
            logger.info("%s: using the embedded all-in-focus original photo", name)
    photo.disparity = disparity
    photo.focus = dinfo.get("focus")
    photo.depth_info = dinfo
    logger.debug("%s: embedded depth found (%s)", name, dinfo["source"])
    return photo


__all__ = [
    "Photo",
    "extract_xmp",
    "jpeg_segments",
    "load_photo",
    "read_embedded_depth",
    "xmp_properties",
    "xmp_regions",
]
