"""The accelerators omg plans for and measures against, in one table (``GPUS``), and what this process's
device can do and took: its dense bf16 peak (``device_peak_tflops``, for MFU) and its peak memory
(``peak_memory``). ``omg bench plan`` sizes runs with the table; ``omg bench train`` and ``omg bench gpu``
read the device's figures."""

from __future__ import annotations

# usable memory (GiB) and dense bf16 peak (TFLOP/s, without 2:4 sparsity), from the NVIDIA datasheets
# (H100 Tensor Core GPU datasheet, SXM and PCIe columns; H200 datasheet; A100 datasheet; L40S datasheet;
# A10G: AWS's G5 instance page). A name's dash-separated parts all appear in the device names it covers.
GPUS: dict[str, tuple[float, float]] = {
    "H100": (80.0, 989.0),  # H100 SXM 80 GB
    "H100-PCIe": (80.0, 756.0),
    "H200": (141.0, 989.0),
    "A100": (80.0, 312.0),  # A100 SXM 80 GB
    "A100-40GB": (40.0, 312.0),
    "L40S": (48.0, 362.0),
    "A10G": (24.0, 125.0),
}


def gpu_kind(device_name: str) -> str | None:
    """The ``GPUS`` entry of a CUDA device named ``device_name`` (``torch.cuda.get_device_name()``), the most
    specific that matches ("NVIDIA H100 PCIe" is H100-PCIe, "NVIDIA H100 80GB HBM3" H100); None when unknown."""
    name = device_name.upper()
    matching = [kind for kind in GPUS if all(part.upper() in name for part in kind.split("-"))]
    return max(matching, key=lambda kind: len(kind.split("-")), default=None)


def device_peak_tflops() -> tuple[str, float | None]:
    """The device's name ("cpu" without a GPU) and its dense bf16 peak in TFLOP/s, None where omg does
    not know it (``GPUS``)."""
    import torch

    if not torch.cuda.is_available():
        return "cpu", None
    name = torch.cuda.get_device_name()
    kind = gpu_kind(name)
    return name, GPUS[kind][1] if kind else None


def peak_memory() -> str:
    """The peak memory so far: allocated on the GPU where there is one, else the process's maximum RSS."""
    import torch

    if torch.cuda.is_available():
        return f"{torch.cuda.max_memory_allocated() / 2**30:.1f} GiB (GPU)"
    import resource

    return f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.1f} GiB (RSS)"
