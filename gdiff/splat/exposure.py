"""Per-image colour correction for the fit: exposure and white balance of each photo.

Cameras with auto exposure and auto white balance record the same surface with other gains
in every photo, and the gains differ between two visits. Fitted without a correction, the
4D model learns those differences as colour changes over time, or as view-dependent colour
(floaters, wrong SH), and the compare stage may take them for changes.

Each training image ``i`` gets an affine colour transform applied to the rendered image
before the photometric loss::

    corrected[y, x, :] = A_i @ rendered[y, x, :] + b_i        A_i [3, 3], b_i [3]

initialised at the identity (``A_i = I``, ``b_i = 0``) and pulled back towards it by
``weight * (|A_i - I|^2 + |b_i|^2)`` (squared Frobenius / Euclidean norms), which also
settles the gauge between the model's colours and the transforms: a gain shared by every
photo stays in the model. The transforms model the camera, not the scene: sequences, change
maps and PLY files are rendered without them (the model's colours are those of a photo with
the identity transform). Colours are the sRGB-encoded values the model is fitted to (see
docs/design.md), so a transform is an affine approximation of a gain in that encoding.
:func:`affine_colour_match` fits one such transform to a render by least squares, to compare
the render with a photo of another exposure (the fit's ``psnr_other_time``).
"""

from __future__ import annotations

import pandas as pd
import torch
from torch import nn


class ExposureCorrection(nn.Module):
    """Affine colour transforms of ``n_images`` training images (see module docstring).

    Parameters: ``matrix`` [n_images, 3, 3] (identity at start), ``bias`` [n_images, 3]
    (zero at start). Images are [H, W, 3] tensors.
    """

    def __init__(self, n_images: int):
        super().__init__()
        if n_images < 1:
            raise ValueError(f"ExposureCorrection needs at least one image, got {n_images}")
        self.matrix = nn.Parameter(torch.eye(3).repeat(n_images, 1, 1))
        self.bias = nn.Parameter(torch.zeros(n_images, 3))

    def __len__(self) -> int:
        return int(self.matrix.shape[0])

    def forward(self, image: torch.Tensor, index: int) -> torch.Tensor:
        """``image`` [H, W, 3] rendered -> [H, W, 3] as photo ``index`` recorded it."""
        return image @ self.matrix[index].T + self.bias[index]

    def regularizer(self, index: int) -> torch.Tensor:
        """Squared distance of transform ``index`` from the identity (a scalar)."""
        eye = torch.eye(3, device=self.matrix.device, dtype=self.matrix.dtype)
        return ((self.matrix[index] - eye) ** 2).sum() + (self.bias[index] ** 2).sum()

    @torch.no_grad()
    def table(self, images: list[str]) -> pd.DataFrame:
        """One row per image: its name, the 9 matrix entries ``a00..a22`` (row-major), the bias
        ``b0..b2`` and ``gain``, the mean of the matrix's diagonal (1 = as the model)."""
        if len(images) != len(self):
            raise ValueError(f"{len(images)} image names for {len(self)} transforms")
        m = self.matrix.detach().cpu().reshape(-1, 9).numpy()
        b = self.bias.detach().cpu().numpy()
        rows = []
        for name, mi, bi in zip(images, m, b):
            row = {"image": name}
            row.update({f"a{r}{c}": float(mi[3 * r + c]) for r in range(3) for c in range(3)})
            row.update({f"b{k}": float(bi[k]) for k in range(3)})
            row["gain"] = float((mi[0] + mi[4] + mi[8]) / 3.0)
            rows.append(row)
        return pd.DataFrame(rows)


def affine_colour_match(pred: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
    """``pred`` [H, W, 3] with its colours mapped onto ``image`` [H, W, 3] by the one affine
    transform (3 x 3 matrix and offset, least squares over every pixel) that fits best,
    clamped to [0, 1]: a render compared with a photo of another exposure and white balance."""
    x = pred.reshape(-1, 3)
    X = torch.cat([x, torch.ones_like(x[:, :1])], dim=1)  # [P, 4]
    M = torch.linalg.lstsq(X.double(), image.reshape(-1, 3).double()).solution  # [4, 3]
    return (X.double() @ M).to(pred.dtype).clamp(0, 1).reshape(image.shape)


__all__ = ["ExposureCorrection", "affine_colour_match"]
