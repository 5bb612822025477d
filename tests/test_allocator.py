"""keep_freed_memory: frame-sized temporaries stop costing page faults on every render."""

from __future__ import annotations

import platform
import subprocess
import sys
import textwrap

import pytest

from d2f_core.allocator import keep_freed_memory

GLIBC = sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc"

# renders a 1024x1536 frame (5-channel layers of 31 MB and more, above glibc's largest mmap
# threshold) and prints the minor page faults per render after two warm-up renders
SCRIPT = textwrap.dedent(
    """
    import resource, sys, torch
    from d2f_core.allocator import keep_freed_memory
    from d2f_core.rendering import render
    applied = keep_freed_memory() if sys.argv[1] == "1" else False
    torch.set_num_threads(1)
    g = torch.Generator().manual_seed(0)
    img = torch.rand(1, 3, 1024, 1536, generator=g) * 0.9
    disp = torch.rand(1, 1, 1024, 1536, generator=g)
    with torch.no_grad():
        for _ in range(2):  # warm-up: the heap grows to what a render needs
            render(img, disp, 0.5, 20.0)
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        for _ in range(2):
            render(img, disp, 0.5, 20.0)
    after = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    print(applied, (after - before) / 2)
    """
)


def _faults_per_render(keep: bool, env: dict[str, str] | None = None) -> tuple[bool, float]:
    out = subprocess.run(
        [sys.executable, "-c", SCRIPT, "1" if keep else "0"],
        capture_output=True,
        text=True,
        check=True,
        timeout=300,
        env=env,
    ).stdout.split()
    return out[0] == "True", float(out[1])


@pytest.mark.skipif(not GLIBC, reason="mallopt settings exist in glibc only")
def test_freed_memory_is_reused_instead_of_faulted_in_again():
    applied, kept = _faults_per_render(True)
    not_applied, plain = _faults_per_render(False)
    assert applied and not not_applied
    # measured: 17000-42000 faults per render by default, 0-1 with the setting
    assert plain > 5000
    assert kept < plain / 4


@pytest.mark.skipif(not GLIBC, reason="mallopt settings exist in glibc only")
def test_environment_turns_it_off(monkeypatch):
    monkeypatch.setenv("D2F_KEEP_FREED_MEMORY", "0")
    assert keep_freed_memory() is False


def test_other_platforms_are_left_alone(monkeypatch):
    monkeypatch.setattr(sys, "platform", "darwin")
    assert keep_freed_memory() is False
