"""Devices every kernel test runs on: the CPU always, CUDA when present."""

import warp as wp


def devices():
    return ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])
