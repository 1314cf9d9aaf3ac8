"""`--fidelity` presets: named trades of speed against accuracy for `grid` and `search`.

Each preset is a setting of knobs `falsify tradeoff` measured on configs/tradeoff.toml (the
README records the figures). The network dominates the time per sample, so the presets that
save time change the bundled model's precision and CRF iterations; a preset with a `--model` of
one's own is refused (it would run that model as given under the preset's name). The car mesh
level of detail stays full in every preset: coarser meshes saved under 1 % of a sample's time
and added map error (measured with `--knobs preset`).
"""

from __future__ import annotations

from dataclasses import dataclass

from falsify.errors import FalsifyError
from falsify.models.runners import WEIGHTS_DIR, resolve_model


@dataclass(frozen=True)
class Fidelity:
    """Car mesh level of detail and which variant of the bundled model to run."""

    name: str
    lod: int = 2
    bundled_model: str = "squeezeseg.onnx"

    def model(self, user_model: str | None) -> str | None:
        """The model a run uses: the user's as given, else this preset's bundled variant."""
        if user_model is not None or self.bundled_model == "squeezeseg.onnx":
            return user_model
        return str(WEIGHTS_DIR / self.bundled_model)

    def is_variant(self, user_model: str) -> bool:
        """Whether `user_model` (a path or a bundled name) is this preset's own variant, as a
        stopped run's resume command names it beside the preset."""
        try:
            given = resolve_model(user_model)
        except FalsifyError:
            return False
        return given.resolve() == (WEIGHTS_DIR / self.bundled_model).resolve()


PRESETS = {
    # reference: ONNX Runtime fp32, 3 CRF iterations
    "exact": Fidelity("exact"),
    # int8 network (CRF kept fp32), 3 CRF iterations
    "balanced": Fidelity("balanced", bundled_model="squeezeseg-int8.onnx"),
    # int8 network, 1 CRF iteration
    "fast": Fidelity("fast", bundled_model="squeezeseg-int8-crf1.onnx"),
    # int8 network without the CRF (a logit-adjusted network needs it least)
    "fastest": Fidelity("fastest", bundled_model="squeezeseg-int8-crf0.onnx"),
}


def preset(name: str) -> Fidelity:
    if name not in PRESETS:
        raise FalsifyError(f"--fidelity: unknown preset {name!r}; allowed: {', '.join(PRESETS)}")
    return PRESETS[name]
