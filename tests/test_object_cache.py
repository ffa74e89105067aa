"""Per-object caches must not serve a freed object's value to a new object at the same address
(lfcam/measure/cache.py): the suite once got another capture's lattice lookup that way."""

from __future__ import annotations

import gc

import numpy as np
import pytest

from lfcam.measure.cache import ObjectCache
from lfcam.measure.fastfit import pedestal


def test_a_new_object_at_a_freed_address_is_a_miss():
    cache = ObjectCache(1)
    a = np.zeros((64, 64))
    assert cache.get(a, lambda: "a") == "a"
    assert cache.get(a, lambda: "other") == "a"  # a hit while a lives
    b = np.zeros((64, 64))
    # b at a's address, as the allocator may place it once a is freed
    cache._items[id(b)] = cache._items.pop(id(a))
    del a
    gc.collect()
    assert cache.get(b, lambda: "b") == "b"


def test_pedestal_follows_the_image_not_its_address():
    rng = np.random.default_rng(0)
    seen = set()
    for level in (10.0, 50.0, 90.0, 10.0, 50.0):
        img = level + rng.normal(0.0, 1.0, (64, 64))
        seen.add(id(img))
        assert pedestal(img) == pytest.approx(level, abs=0.3)
        del img
