"""``gan_lstm``: the paper's 3D GAN, the completion method the product ships.

A 3D conv encoder-decoder with skips, a 3D conv-LSTM over the views and a conditional WGAN-GP
critic (``models.completion``); it reads the views' three-state grids in order.
"""

from __future__ import annotations

from cadio.registry import Role
from models.completions import COMPLETIONS, CompletionMethod

GAN_LSTM = COMPLETIONS.register(CompletionMethod(
    "gan_lstm", "3D GAN: conv encoder-decoder, 3D conv-LSTM over the views, WGAN-GP critic",
    Role.OURS, 0, __name__, model_input=lambda example: example.inputs,
    config="models.completion:CompletionConfig"))
