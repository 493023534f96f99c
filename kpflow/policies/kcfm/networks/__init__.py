"""The K-CFM's denoising networks: a 1-D temporal U-Net and a small transformer, both FiLM-conditioned."""
