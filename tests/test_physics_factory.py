"""make_backend: names, parameters, pools and caches."""

import pytest

from overhang_framework.physics import PhysicsBackend
from overhang_framework.physics.cache import CachedBackend, VerdictCache
from overhang_framework.physics.factory import make_backend


def test_static_with_params():
    backend = make_backend("static", margin=0.02)
    assert backend.name == "static" and backend.params.margin == 0.02
    assert isinstance(backend, PhysicsBackend)


def test_pybullet_with_params():
    pytest.importorskip("pybullet")
    backend = make_backend("pybullet", duration=1.0)
    assert backend.name == "pybullet" and backend.params.duration == 1.0


def test_unknown_name_lists_allowed_names_on_one_line():
    with pytest.raises(ValueError) as err:
        make_backend("bullet")
    msg = str(err.value)
    assert "\n" not in msg and "pybullet" in msg and "static" in msg


def test_unknown_parameter_is_an_error():
    with pytest.raises(ValueError, match="margn"):
        make_backend("static", margn=0.1)


def test_cache_option_wraps_and_shares():
    cache = VerdictCache()
    a = make_backend("static", cache=cache)
    b = make_backend("static", cache=cache)
    assert isinstance(a, CachedBackend) and a.cache is b.cache
    assert isinstance(make_backend("static", cache=True), CachedBackend)
