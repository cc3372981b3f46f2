"""Compiled kernels are cached against all the source they draw on, not only their own file."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

from dm2.core.kernel_cache import kernel_sources, source_key

RUN = "import kpkg.outer as o; print(o.outer(), sum(o.outer.stats.cache_hits.values()))"


def _package(root: Path) -> Path:
    """A package that keys its caches as dm2 does: the cached kernel ``outer`` (outer.py)
    inlines ``inner`` (inner.py), which returns the constant ``VALUE`` of consts.py (no
    compiled code there); cli.py only calls the kernel."""
    pkg = root / "kpkg"
    pkg.mkdir()
    files = {
        "__init__.py": """
            from pathlib import Path

            from dm2.core.kernel_cache import key_kernel_caches

            key_kernel_caches((Path(__file__).parent,), (Path(__file__).parent,))
            """,
        "consts.py": """
            VALUE = 1
            """,
        "inner.py": """
            from numba import njit

            from kpkg.consts import VALUE


            @njit(inline="always")
            def inner():
                return VALUE
            """,
        "outer.py": """
            from numba import njit

            from kpkg.inner import inner


            @njit(cache=True)
            def outer():
                return inner()
            """,
        "cli.py": """
            from kpkg.outer import outer

            print(outer())
            """,
    }
    for name, text in files.items():
        (pkg / name).write_text(textwrap.dedent(text))
    return pkg


def _run(root: Path) -> tuple[int, int]:
    """``(outer(), cache hits)`` in a fresh interpreter."""
    out = subprocess.run([sys.executable, "-c", RUN], cwd=root, capture_output=True, text=True,
                         check=True)
    value, hits = out.stdout.split()
    return int(value), int(hits)


def test_a_kernel_is_compiled_again_when_a_constant_it_inlines_changes(tmp_path):
    """numba alone checks only outer.py and would load the old machine code (1) after the edit
    of consts.py; keyed, the kernel is compiled again and its cache saved over."""
    pkg = _package(tmp_path)
    assert _run(tmp_path) == (1, 0)  # compiled and saved
    assert _run(tmp_path) == (1, 1)  # loaded from the cache
    consts = pkg / "consts.py"
    consts.write_text(consts.read_text().replace("VALUE = 1", "VALUE = 2"))
    assert _run(tmp_path) == (2, 0)  # the old machine code is not loaded
    assert _run(tmp_path) == (2, 1)  # the new one is cached in its place
    assert len(list((pkg / "__pycache__").glob("outer.outer-*.nbi"))) == 1
    (pkg / "cli.py").write_text((pkg / "cli.py").read_text() + "\n# edited\n")
    assert _run(tmp_path) == (2, 1)  # a file no compiled code draws on: still cached


def test_the_key_covers_the_compiled_files_and_what_they_import_and_nothing_else(tmp_path):
    pkg = _package(tmp_path).resolve()
    assert kernel_sources((pkg,)) == sorted(pkg / n for n in ("__init__.py", "consts.py",
                                                               "inner.py", "outer.py"))
    key = source_key((pkg,))
    assert source_key((pkg,)) == key and len(key) == 16
    (pkg / "notes.txt").write_text("not source")
    (pkg / "cli.py").write_text("print(2)\n")
    assert source_key((pkg,)) == key
    (pkg / "consts.py").write_text((pkg / "consts.py").read_text() + "\n")
    changed = source_key((pkg,))
    assert changed != key
    (pkg / "inner.py").rename(pkg / "inner2.py")  # the path counts too (outer's import breaks)
    assert source_key((pkg,)) not in (key, changed)


def test_dm2_and_twin_kernels_carry_the_key():
    """dm2's kernels are keyed by dm2's source; the twin's by dm2's and its own (it may compile
    dm2's functions in)."""
    import twin
    from dm2.fusion.tsdf import kernels
    from twin.world import heightfield_kernels

    dm2_dir, twin_dir = Path(kernels.__file__).parents[2], Path(twin.__file__).parent
    assert dm2_dir / "fusion" / "tsdf" / "ray_walk.py" in kernel_sources((dm2_dir,))
    assert dm2_dir / "cli" / "main.py" not in kernel_sources((dm2_dir,))
    for kernel, sources in ((kernels.fuse_profiles, (dm2_dir,)),
                            (heightfield_kernels.raycast_serial, (dm2_dir, twin_dir))):
        locator = kernel._cache._impl.locator
        assert type(locator).__name__ == "KeyedInTreeCacheLocator"
        assert locator.get_source_stamp()[1] == source_key(sources)
