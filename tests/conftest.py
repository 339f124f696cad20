import warp as wp

wp.config.log_level = wp.LOG_WARNING
wp.init()


def devices():
    """Devices every kernel test runs on: the CPU always, CUDA when present."""
    return ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])
