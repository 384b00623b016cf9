"""Device layer and kernel loader (issue: foundation)."""

from __future__ import annotations

import numpy as np
import pyopencl as cl
import pytest
from triplet_cl.cli.main import main as cli_main

from triplet_cl import device as devmod
from triplet_cl.device import Device, get_device, list_devices, resolve_spec
from triplet_cl.errors import DeviceSelectionError, KernelBuildError


def test_list_devices_reports_fields():
    infos = list_devices()
    assert infos, "at least one OpenCL device (PoCL in CI)"
    for i in infos:
        assert i.compute_units > 0 and i.global_mem_bytes > 0 and i.max_alloc_bytes > 0
        assert i.type in {"GPU", "CPU", "ACCELERATOR", "OTHER"}
        assert i.opencl_c_version


def test_select_by_index_and_name(monkeypatch):
    monkeypatch.delenv("TRIPLET_DEVICE", raising=False)
    first = list_devices()[0]
    info, _, _ = resolve_spec(first.index)
    assert info.index == first.index
    # a substring of the device name, in another case
    info2, _, _ = resolve_spec(first.device_name[:6].upper())
    assert info2.device_name[:6].lower() == first.device_name[:6].lower()
    # a substring of the platform name
    info3, _, _ = resolve_spec(first.platform_name.split()[0].lower())
    assert first.platform_name.split()[0].lower() in info3.full_name.lower()


def test_select_from_environment(monkeypatch):
    first = list_devices()[0]
    monkeypatch.setenv("TRIPLET_DEVICE", first.index)
    info, _, _ = resolve_spec(None)
    assert info.index == first.index
    monkeypatch.setenv("TRIPLET_DEVICE", "no-such-device-xyz")
    with pytest.raises(DeviceSelectionError):
        resolve_spec(None)


def test_default_prefers_gpu_then_cpu(monkeypatch):
    monkeypatch.delenv("TRIPLET_DEVICE", raising=False)
    infos = list_devices()
    info, _, _ = resolve_spec(None)
    gpus = [i for i in infos if i.type == "GPU"]
    cpus = [i for i in infos if i.type == "CPU"]
    expected = gpus[0] if gpus else (cpus[0] if cpus else infos[0])
    assert info.index == expected.index


def test_no_match_lists_devices(monkeypatch):
    monkeypatch.delenv("TRIPLET_DEVICE", raising=False)
    with pytest.raises(DeviceSelectionError) as ei:
        resolve_spec("definitely-not-a-device")
    msg = str(ei.value)
    assert "definitely-not-a-device" in msg
    assert list_devices()[0].device_name in msg  # the error lists what exists
    with pytest.raises(DeviceSelectionError, match="does not exist"):
        resolve_spec("97:3")


def test_get_device_is_one_object_per_device(device):
    assert get_device(device.info.index) is device


@pytest.mark.parametrize("real", [np.float32, np.float64])
def test_reduction_kernel_matches_numpy(device, rng, real):
    if real == np.float64 and not device.fp64:
        pytest.skip("no fp64 on this device")
    n, groups, lsz = 10_007, 8, 64
    x = rng.standard_normal(n).astype(real)
    mf = cl.mem_flags
    x_buf = cl.Buffer(device.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=x)
    out = np.empty(groups, real)
    out_buf = cl.Buffer(device.ctx, mf.WRITE_ONLY, out.nbytes)
    k = device.kernel("reduce", "block_sum_fwd", real=real)
    k(device.queue, (groups * lsz,), (lsz,), x_buf, np.int32(n), out_buf, cl.LocalMemory(lsz * x.itemsize))
    cl.enqueue_copy(device.queue, out, out_buf)
    tol = 1e-4 if real == np.float32 else 1e-11
    np.testing.assert_allclose(out.sum(), x.astype(np.float64).sum(), rtol=tol, atol=tol)
    # and the adjoint: v_x = v_out[group of x]
    v_out = rng.standard_normal(groups).astype(real)
    v_out_buf = cl.Buffer(device.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=v_out)
    v_x = np.empty(n, real)
    v_x_buf = cl.Buffer(device.ctx, mf.WRITE_ONLY, v_x.nbytes)
    kb = device.kernel("reduce", "block_sum_bwd", real=real)
    kb(device.queue, (groups * lsz,), (lsz,), v_out_buf, np.int32(n), v_x_buf)
    cl.enqueue_copy(device.queue, v_x, v_x_buf)
    expected = v_out[(np.arange(n) % (groups * lsz)) // lsz]
    np.testing.assert_array_equal(v_x, expected)


def test_build_error_names_file_options_and_log(device, tmp_path, monkeypatch):
    (tmp_path / "common").mkdir()
    (tmp_path / "broken.cl").write_text("__kernel void f(__global float* x) { x[0] = 1.0f +; }\n")
    monkeypatch.setattr(devmod, "kernel_dir", lambda: tmp_path)
    d = Device(device.info, device.platform, device.cl_device)
    with pytest.raises(KernelBuildError) as ei:
        d.program("broken", defines={"K_MAX": 30})
    e = ei.value
    assert e.path.endswith("broken.cl")
    assert "-DK_MAX=30" in e.options and "-DREAL=float" in e.options
    assert "broken.cl" in str(e) and "-DK_MAX=30" in str(e)
    assert "error" in e.log.lower() and e.log in str(e)


def test_missing_kernel_file(device):
    with pytest.raises(FileNotFoundError, match="no_such_op"):
        device.program("no_such_op")


def test_loader_builds_each_program_once(device):
    d = Device(device.info, device.platform, device.cl_device)  # a fresh memo
    assert d.build_count == 0
    k1 = d.kernel("reduce", "block_sum_fwd")
    k2 = d.kernel("reduce", "block_sum_fwd")
    d.kernel("reduce", "block_sum_bwd")
    assert k1 is k2
    assert d.build_count == 1
    d.kernel("reduce", "block_sum_fwd", defines={"K_MAX": 7})  # new options: a new program
    assert d.build_count == 2
    d.program("reduce", defines={"K_MAX": 7})
    assert d.build_count == 2
    assert len(d._programs) == 2


def test_bad_define_name_is_rejected(device):
    with pytest.raises(ValueError, match="define"):
        device.program("reduce", defines={"BAD NAME": 1})


def test_cli_devices(capsys, device):
    assert cli_main(["devices"]) == 0
    out = capsys.readouterr().out
    assert device.info.device_name in out and "chosen" in out and "fp64" in out
    assert cli_main(["devices", "--device", "no-such-device-xyz"]) == 2
    assert "no-such-device-xyz" in capsys.readouterr().err


def test_alloc_check(device):
    with pytest.raises(MemoryError, match="depth buffer"):
        device.check_alloc(device.info.max_alloc_bytes + 1, "depth buffer")


def test_pool_gives_back_held_buffers_past_its_limit(device):
    """``Device.release_held``: buffers of many sizes freed into the pool (a render's buffers change size with its
    fragment count) are given back once they exceed the limit; below it the pool keeps them for reuse; buffers in
    use are never touched."""
    import pyopencl.array as cla

    pool = device.allocator
    pool.free_held()
    live = cla.empty(device.queue, 1000, np.float32, allocator=pool)
    for n in (3000, 5000, 9000, 17000):  # four size classes, freed
        cla.empty(device.queue, n, np.float32, allocator=pool).finish()
    held = int(pool.managed_bytes) - int(pool.active_bytes)
    assert held >= 4 * 34000 and pool.held_blocks >= 4
    assert device.release_held(limit_bytes=held) == 0  # at the limit: kept
    assert int(pool.managed_bytes) - int(pool.active_bytes) == held
    assert device.release_held(limit_bytes=1000) == held
    assert pool.held_blocks == 0 and pool.active_blocks >= 1  # buffers in use stay (the live one: below)
    live.fill(1.0)
    assert float(live.get().sum()) == 1000.0


def test_release_memory_gives_back_every_held_buffer(device):
    """``Device.release_memory`` (between phases): the pool holds nothing afterwards, buffers in use stay."""
    import pyopencl.array as cla

    pool = device.allocator
    live = cla.empty(device.queue, 500, np.float32, allocator=pool)
    cla.empty(device.queue, 7000, np.float32, allocator=pool).finish()
    assert pool.held_blocks >= 1
    device.release_memory()  # its gc may free other tests' unreferenced arrays too: only the live one must stay
    assert pool.held_blocks == 0 and pool.active_blocks >= 1
    live.fill(2.0)
    assert float(live.get().sum()) == 1000.0


def test_release_memory_waits_for_a_large_process(device):
    """``release_memory(min_resident)``: nothing released while the process is smaller (the training loop's
    densifications at small captures), everything past it."""
    import pyopencl.array as cla

    from triplet_cl.device import resident_bytes

    assert resident_bytes() > 0
    pool = device.allocator
    cla.empty(device.queue, 7000, np.float32, allocator=pool).finish()
    held = pool.held_blocks
    assert held >= 1
    device.release_memory(min_resident=1 << 50)
    assert pool.held_blocks == held
    device.release_memory(min_resident=1)
    assert pool.held_blocks == 0


def test_kernels_declare_their_scalar_types(device):
    # session 62: PyOpenCL hands an undeclared numpy scalar to clSetKernelArg through the buffer protocol (~7 µs an
    # argument on every launch, ~120 a training step); Device.kernel declares the by-value parameters' types from the
    # signature, so a launch packs them. The same bytes reach the kernel: numpy scalars of the declared types and plain
    # Python numbers give bit-identical results, which the undeclared path could not take at all (a Python float has
    # no fixed size)
    import pyopencl.array as cla

    k = device.kernel("adam", "adam_step", real=np.float32)
    assert devmod.declare_scalar_types(k, "adam", "adam_step", None, np.float32)
    rng = np.random.default_rng(3)
    x0, m0, v0, g = (rng.standard_normal(100).astype(np.float32) for _ in range(4))
    v0 = np.abs(v0)
    scalars = (1.0, 0.9, 0.1, 0.999, 0.001, 0.01, 0.5, 1e-8)
    outs = []
    for conv in (np.float32, float):
        arrs = [cla.to_device(device.queue, a.copy()) for a in (x0, m0, v0)]
        flag = cla.zeros(device.queue, 1, np.int32)
        k(device.queue, (128,), None, *[a.data for a in arrs], cla.to_device(device.queue, g).data, np.int32(100),
          *(conv(s) for s in scalars), flag.data)
        outs.append([a.get() for a in arrs])
    for a, b in zip(*outs, strict=True):
        assert np.array_equal(a, b) and not np.array_equal(a, x0)
    # a signature the parser cannot read (columns.cl: a macro in the parameter list), or one whose parameter count is
    # not the built kernel's, leaves the kernel undeclared (the plain path)
    assert not devmod.declare_scalar_types(k, "columns", "merge_columns", None, np.float32)
    assert not devmod.declare_scalar_types(k, "density", "face_stats_add", None, np.float32)
