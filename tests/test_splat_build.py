"""The C++ splat kernel's build cache: one folder per torch installation, one stderr line only when it compiles."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from t2bs.render.splat import cpu  # noqa: E402


def test_build_directory_is_keyed_by_the_torch_installation(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setattr(torch, "__file__", "/envs/a/lib/python3.11/site-packages/torch/__init__.py")
    a = cpu.build_directory()
    assert cpu.build_directory() == a  # stable: the same installation finds its build again
    assert a.parent == tmp_path / "t2bs" / "torch_extensions"
    monkeypatch.setattr(torch, "__file__", "/envs/b/lib/python3.11/site-packages/torch/__init__.py")
    b = cpu.build_directory()
    monkeypatch.setattr(torch, "__version__", "0.0.1+test")
    c = cpu.build_directory()
    assert len({a.name, b.name, c.name}) == 3, (a, b, c)
    assert c.name.startswith("splat_cpu_torch0.0.1_test_")


@pytest.fixture
def fake_build(monkeypatch, tmp_path):
    """A kernel that is not loaded yet, a cache in tmp_path, and a build function that writes the module file."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setattr(cpu, "_module", None)
    monkeypatch.setattr(cpu, "_error", None)
    calls = []

    def compile_(path, openmp=True):
        calls.append(path)
        (path / "t2bs_splat_cpu.so").write_bytes(b"")
        return object()

    monkeypatch.setattr(cpu, "_compile", compile_)
    return calls


def test_build_message_only_when_it_compiles(fake_build, capsys, monkeypatch):
    module = cpu.load_kernel()
    assert module is not None and cpu.load_kernel() is module  # loaded once per process
    err = capsys.readouterr().err
    assert err.splitlines() == [cpu.BUILD_MESSAGE]
    assert (
        cpu.BUILD_MESSAGE
        == "t2bs: compiling the C++ splat kernel (first use with this torch installation, ~1-3 min)..."
    )
    # A new process (module not loaded) finds the cached build: it loads without the message.
    monkeypatch.setattr(cpu, "_module", None)
    assert cpu.load_kernel() is not None
    assert capsys.readouterr().err == ""
    assert len(fake_build) == 2 and fake_build[0] == fake_build[1] == cpu.build_directory()


def test_failed_build_says_why(fake_build, capsys, monkeypatch):
    def broken(path, openmp=True):
        raise RuntimeError("Error building extension 't2bs_splat_cpu'\nc++: not found")

    monkeypatch.setattr(cpu, "_compile", broken)
    assert cpu.load_kernel() is None
    assert cpu.kernel_error() == "RuntimeError: c++: not found"
    assert capsys.readouterr().err.splitlines() == [cpu.BUILD_MESSAGE]


def test_a_compiler_without_openmp_builds_on_plain_threads(fake_build, capsys, monkeypatch):
    built = []

    def no_openmp(path, openmp=True):
        if openmp:
            raise RuntimeError("Error building extension 't2bs_splat_cpu'\nc++: error: unsupported option '-fopenmp'")
        built.append(path)
        (path / "t2bs_splat_cpu.so").write_bytes(b"")
        return object()

    monkeypatch.setattr(cpu, "_compile", no_openmp)
    assert cpu.load_kernel() is not None and cpu.kernel_error() is None
    assert built == [cpu.build_directory(openmp=False)] and built[0] != cpu.build_directory()
    assert capsys.readouterr().err.splitlines() == [cpu.BUILD_MESSAGE]  # announced once, not per attempt
