"""Neural building blocks shared by every policy (encoders, attention, the diffusion U-Net)."""
