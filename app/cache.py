"""A process-wide, memory-bounded LRU cache of prepared scenes, keyed by content.

``D2F.prepare`` runs the networks once per photo. Re-uploading the same pixels (with the
same user depth map, if any) -- in any session -- returns the cached ``Scene`` at once.

Memory bound: the cache holds at most ``max_bytes`` of scene tensors/arrays (counted by
:func:`scene_nbytes`), 384 MiB by default, or ``D2F_APP_CACHE_MB`` MiB from the environment.
The least recently used scenes are dropped first; a scene larger than the whole bound is
returned but not kept. Sizes are re-counted on every access because a scene fills its own
lazy caches (full-resolution disparity, preview inputs) after it was stored; the most
recently used scene is kept even when that growth alone passes the bound. Scenes that
sessions still hold in their ``gr.State`` stay alive until the session ends, so peak
memory is this bound plus the scenes of active sessions.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import os
import threading
import weakref
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

log = logging.getLogger(__name__)

#: the scene cache's default bound (``D2F_APP_CACHE_MB``): 40 sessions of 1600x1200 photos grew
#: the server by 1.7-1.9 GB with a 1 GiB bound, 1.33-1.34 GB with 512 MiB, 1.13-1.18 GB with
#: 384 MiB, 1.1 GB with 256 MiB
DEFAULT_MAX_BYTES = 384 << 20


def content_key(image: np.ndarray, disparity: np.ndarray | None = None) -> str:
    """sha256 over the pixels (and the user's disparity map, if any), with their shapes."""
    h = hashlib.sha256()
    for a in (image, disparity):
        if a is None:
            h.update(b"none")
            continue
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(memoryview(a).cast("B"))
    return h.hexdigest()


def scene_nbytes(obj: Any, _seen: set[int] | None = None) -> int:
    """Bytes held by the tensors and arrays of a scene (dataclass fields, dicts, lists)."""
    seen = set() if _seen is None else _seen
    if id(obj) in seen:
        return 0
    seen.add(id(obj))
    if isinstance(obj, torch.Tensor):
        return obj.numel() * obj.element_size()
    if isinstance(obj, np.ndarray):
        return obj.nbytes
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return sum(scene_nbytes(getattr(obj, f.name), seen) for f in dataclasses.fields(obj))
    if isinstance(obj, dict):
        return sum(scene_nbytes(v, seen) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return sum(scene_nbytes(v, seen) for v in obj)
    return 0


class SceneCache:
    """Thread-safe LRU of prepared scenes, bounded by their total size in bytes.

    Keys combine the model (each model object gets its own token) and :func:`content_key`.
    Concurrent requests for the same key prepare once; the others wait for that result.
    """

    def __init__(self, max_bytes: int = DEFAULT_MAX_BYTES) -> None:
        if max_bytes < 0:
            raise ValueError(f"max_bytes must be >= 0, got {max_bytes}")
        self.max_bytes = int(max_bytes)
        self._items: OrderedDict[tuple[int, str], tuple[Any, int]] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self._pending: dict[tuple[int, str], threading.Lock] = {}
        self._tokens: weakref.WeakKeyDictionary[Any, int] = weakref.WeakKeyDictionary()
        self._next_token = 0
        self.hits = 0
        self.misses = 0

    @property
    def nbytes(self) -> int:
        """Bytes currently held."""
        return self._bytes

    def __len__(self) -> int:
        return len(self._items)

    def _token(self, model: Any) -> int:
        # one token per live model object: two models never share entries, even if a
        # later model happens to reuse a freed object's id()
        with self._lock:
            tok = self._tokens.get(model)
            if tok is None:
                self._next_token += 1
                tok = self._tokens[model] = self._next_token
            return tok

    def get(self, model: Any, key: str) -> Any | None:
        """The cached scene for ``(model, key)``, or None; marks it recently used."""
        k = (self._token(model), key)
        with self._lock:
            item = self._items.get(k)
            if item is None:
                return None
            self._items.move_to_end(k)
            self._remeasure()
            return item[0]

    def _remeasure(self) -> None:
        # scenes fill their own caches lazily (full-res disparity, preview inputs) after
        # they were put here, so sizes are re-counted whenever the cache is touched
        total = 0
        for k, (scene, _) in list(self._items.items()):
            size = scene_nbytes(scene)
            self._items[k] = (scene, size)
            total += size
        self._bytes = total
        while self._bytes > self.max_bytes and len(self._items) > 1:
            _, (_, dropped) = self._items.popitem(last=False)
            self._bytes -= dropped

    def put(self, model: Any, key: str, scene: Any) -> None:
        """Insert a scene and evict least recently used ones beyond ``max_bytes``."""
        k = (self._token(model), key)
        size = scene_nbytes(scene)
        with self._lock:
            if k in self._items:
                self._bytes -= self._items.pop(k)[1]
            if size > self.max_bytes:
                log.info("scene of %d bytes exceeds the cache bound; not cached", size)
                return
            self._items[k] = (scene, size)
            self._remeasure()

    def get_or_prepare(self, model: Any, key: str, prepare: Callable[[], Any]) -> tuple[Any, bool]:
        """Return ``(scene, was_cached)``, calling ``prepare()`` once per missing key."""
        k = (self._token(model), key)
        scene = self.get(model, key)
        if scene is not None:
            self.hits += 1
            return scene, True
        with self._lock:
            gate = self._pending.setdefault(k, threading.Lock())
        with gate:
            scene = self.get(model, key)
            if scene is not None:
                self.hits += 1
                return scene, True
            self.misses += 1
            try:
                scene = prepare()
                self.put(model, key, scene)
            finally:
                with self._lock:
                    self._pending.pop(k, None)
        return scene, False

    def clear(self) -> None:
        """Drop every entry."""
        with self._lock:
            self._items.clear()
            self._bytes = 0


def _bound_from_env() -> int:
    raw = os.environ.get("D2F_APP_CACHE_MB")
    if not raw:
        return DEFAULT_MAX_BYTES
    try:
        return max(0, int(float(raw) * (1 << 20)))
    except ValueError:
        log.warning("ignoring D2F_APP_CACHE_MB=%r (not a number)", raw)
        return DEFAULT_MAX_BYTES


#: The cache shared by every app built in this process (see the module docstring).
SCENE_CACHE = SceneCache(_bound_from_env())
