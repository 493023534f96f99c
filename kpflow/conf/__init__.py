"""kpflow's Hydra configs (``config_path="pkg://kpflow.conf"``): one folder per config group, one YAML per option."""
