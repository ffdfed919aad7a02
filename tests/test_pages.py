"""dicer.pages: the commands' arrays in ordinary memory pages unless the user asks numpy otherwise."""

import pytest

from dicer.pages import _switch, ordinary_pages

switch = _switch()
pytestmark = pytest.mark.skipif(switch is None, reason="this numpy has no huge-page switch")


def current() -> bool:
    previous = switch(False)
    switch(previous)
    return bool(previous)


def test_ordinary_pages_inside_the_block_and_numpy_choice_restored_after(monkeypatch):
    monkeypatch.delenv("NUMPY_MADVISE_HUGEPAGE", raising=False)
    before = switch(True)
    try:
        with ordinary_pages(unless_set=True):
            assert current() is False
        assert current() is True
        with pytest.raises(RuntimeError), ordinary_pages():
            raise RuntimeError("a failing command")
        assert current() is True
    finally:
        switch(before)


def test_the_users_setting_stands(monkeypatch):
    monkeypatch.setenv("NUMPY_MADVISE_HUGEPAGE", "1")
    before = switch(True)
    try:
        with ordinary_pages(unless_set=True):
            assert current() is True
        with ordinary_pages():  # the voxel mesher's own block ignores it
            assert current() is False
    finally:
        switch(before)
