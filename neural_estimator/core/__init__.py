"""The house's footing (layer 1): angle arithmetic (:mod:`angles`), output files written whole or not
at all (:mod:`atomic`), YAML read in bounded time and memory (:mod:`safe_yaml`), the one grammar of
option values (:mod:`options`), the one-line command-line parser (:mod:`arguments`), ROS interface
checks without rclpy (:mod:`interfaces`) and the allocator (:mod:`runtime`). Nothing here imports
anything of the package above layer 1."""
