"""sudd policy: a language-conditioned diffusion policy distilled from generated episodes.

config (PolicyConfig presets) -> data (samples from datagen.store) -> model / text (torch networks, frozen
MiniLM) -> train (DDPM, EMA, checkpoints, DDP) -> export (ONNX bundle, verified) -> bundle (the runtime's
loader: numpy + onnxruntime + tokenizers only) ; bench (`sudd bench policy`), cli (`sudd train|export`).

Importing this package imports nothing: `policy.bundle` must stay loadable without torch.
"""
