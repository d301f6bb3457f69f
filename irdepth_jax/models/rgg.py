"""RGG: radiation-field gradient guidance (paper section 3.2.2) for one decoder up block.

The paper's equation was lost in extraction; this is our formulation of what the text says
(gradients of the raw input, combined with gradients of the decoder features, through a learnable
task-specific attention that modulates the upsampled decoder features and the encoder skip
features before fusion, balanced by alpha). With U the upsampled decoder features (B, h, w, C),
S the encoder skip features (B, h, w, C), and G the input's GCM map at this scale (B, h, w, 1):

    M_f = Conv1x1_f(GCM(U))                                  feature-gradient guidance
    M_g = Conv3x3_g(G)                                       input-gradient guidance
    A   = sigmoid(Conv1x1_a(ReLU(alpha * M_f + (1 - alpha) * M_g)))     in (0, 1)^(h, w, C)
    U'  = U * (1 + A),   S' = S * (1 + A)

and the block then fuses concat(U', S') with its double conv. The residual form (1 + A) lets the
attention only emphasise structure: at A = 0 the block is the plain UNet, and no channel can
be switched off wholesale at initialisation. Every decoder owns its RGG parameters, which is
what makes the attention task-specific.
"""

from __future__ import annotations

import flax.linen as nn

from irdepth_jax.imaging.gradients import gradient_magnitude


class RGG(nn.Module):
    """Gradient-guided attention of one up block.

    Attributes:
      alpha: weight of the feature-gradient guidance; 1 - alpha weighs the input gradient.
    """

    alpha: float = 0.5

    @nn.compact
    def __call__(self, up, skip, input_grad):
        """Modulates decoder and skip features.

        Args:
          up: (B, h, w, C) upsampled decoder features.
          skip: (B, h, w, C) encoder features of the same scale.
          input_grad: (B, h, w, 1) GCM map of the input image, resized to this scale.

        Returns:
          (up', skip'), both (B, h, w, C): the features scaled by (1 + A).
        """
        if up.shape != skip.shape or input_grad.shape != up.shape[:-1] + (1,):
            raise ValueError(
                f"RGG: expected up and skip (B, h, w, C) of one shape and input_grad (B, h, w, 1), "
                f"got {up.shape}, {skip.shape}, {input_grad.shape}"
            )
        channels = up.shape[-1]
        feature_guidance = nn.Conv(channels, (1, 1), name="feature_proj")(gradient_magnitude(up))
        input_guidance = nn.Conv(channels, (3, 3), name="input_proj")(input_grad)
        mixed = self.alpha * feature_guidance + (1.0 - self.alpha) * input_guidance
        attention = nn.sigmoid(nn.Conv(channels, (1, 1), name="attention")(nn.relu(mixed)))
        return up * (1.0 + attention), skip * (1.0 + attention)
