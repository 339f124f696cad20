import warp as wp

wp.config.log_level = wp.LOG_WARNING
wp.init()
