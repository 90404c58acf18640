"""What the device can do and what a benchmark took of it: the GPU's dense bf16 peak
(``device_peak_tflops``, for MFU) and this process's peak memory (``peak_memory``). ``omg bench
train`` and ``omg bench gpu`` read them from here."""

from __future__ import annotations

# dense bf16 TFLOP/s by a substring of the device name, without 2:4 sparsity (NVIDIA datasheets)
PEAK_TFLOPS = {"H100": 989.0, "H200": 989.0, "A100": 312.0, "L40S": 362.0, "A10G": 125.0}


def peak_memory() -> str:
    """The peak memory so far: allocated on the GPU where there is one, else the process's maximum RSS."""
    import torch

    if torch.cuda.is_available():
        return f"{torch.cuda.max_memory_allocated() / 2**30:.1f} GiB (GPU)"
    import resource

    return f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.1f} GiB (RSS)"


def device_peak_tflops() -> tuple[str, float | None]:
    """The device's name ("cpu" without a GPU) and its dense bf16 peak in TFLOP/s, None where omg does
    not know it (``PEAK_TFLOPS``)."""
    import torch

    if not torch.cuda.is_available():
        return "cpu", None
    name = torch.cuda.get_device_name()
    return name, next((v for k, v in PEAK_TFLOPS.items() if k in name), None)
