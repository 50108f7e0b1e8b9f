"""The tone protocol and its registry: what every path that makes an enhanced image asks of ``model.enhancement.tone``.

A tone turns the rendered R̂, L̂ and the EnhancementNet's g into the enhanced image. Training, the fast renderer,
``render --format exr``, the export bake, the viewer and the loss meter all ask the tone object (never its name)
what to do, so a new tone is one module: a :class:`Tone` subclass with ``@register`` (docs: the package's
``__init__``).
"""
from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar, Dict, Optional, Tuple, Type, TypeVar, Union

import torch
from torch import Tensor

if TYPE_CHECKING:  # types only: the config sections are passed in by the loader
    from retinexgs.config.schema import Enhancement

__all__ = ["Tone", "TONES", "register", "get_tone", "config_problem"]

class Tone:
    """One tone form of the enhancement. Subclasses set the class attributes and implement :meth:`map`; the
    defaults describe a tone with no linear form, no highlight shoulder, no fused kernel and the gamma scaled by
    the user's exposure factor (the gamma tones' rules).

    Attributes:
        name: the value of ``model.enhancement.tone`` that selects it.
        formula: S_enh as text in R, L, L_ref and g (the PLY comment, logs, docs).
        fused_kernel: the ``retinexgs._C`` kernel that renders S_enh from a rasterized [H,W,6] frame in one
            pass, called as ``kernel(image, gain, knee)`` with ``gain`` from :meth:`fused_gain` ([1], [3], or [9]:
            a white balance W·diag(gain) row-major); None: the frame is toned by :meth:`map` in torch.
        meter_applies: ``loss.exp_highlight_share`` (the highlight-protecting exposure meter) caps the exposure
            target of this tone (the meter reads the light as a gain would expose it).
        needs_reference: the tone needs ``model.enhancement.ref_quantile`` (an L_ref below 1).
        gain_curve: S_enh is the training tone curve of R̂∘L̂ at the gain :meth:`fused_gain`, clipped in and out
            (:func:`~retinexgs.model.tones.fused_curve.tone_curve`): L_enhance then runs as two kernels
            (:mod:`retinexgs.train.fused_enhance`).
    """

    name: ClassVar[str] = ""
    formula: ClassVar[str] = ""
    fused_kernel: ClassVar[Optional[str]] = None
    meter_applies: ClassVar[bool] = False
    needs_reference: ClassVar[bool] = False
    gain_curve: ClassVar[bool] = False

    def __eq__(self, other: object) -> bool:
        # A tone compared with a name is a check this registry replaces (``model.tone == "exposure"`` would now be
        # silently False): fail loudly instead, pointing at the attribute to ask.
        if isinstance(other, str):
            raise TypeError(f"a Tone compared with the string {other!r}: ask the tone (its attributes and methods) "
                            "or compare tone.name")
        return self is other

    __hash__ = object.__hash__

    def __repr__(self) -> str:
        return f"<tone {self.name!r}>"

    def map(self, R: Tensor, L: Tensor, illum_ref: Tensor, gamma: Tensor, eps: float = 1e-3,
            shoulder: float = 1.0) -> Tuple[Tensor, Tensor]:
        """(S_enh, L_enh) for R̂ [..., 3] or [B,3,H,W], the rendered L̂ of the same layout, L_ref (a scalar
        tensor) and g (broadcastable against R̂). ``eps``: a floor under powers, so gradients stay finite at 0;
        ``shoulder``: the highlight knee (tones with :meth:`knee`)."""
        raise NotImplementedError(f"tone {self.name!r} has no map")

    def linear(self, R: Tensor, L: Tensor, illum_ref: Tensor, gamma: Tensor) -> Optional[Tensor]:
        """The enhanced linear light before the highlight shoulder and the sRGB curve (what ``render --format exr``
        writes and a white balance acts on), or None: the tone clips before any linear form, and its light is
        lin(S_enh) (the gamma tones)."""
        return None

    def knee(self, shoulder: float) -> float:
        """The highlight knee this tone applies under ``model.enhancement.shoulder`` ``shoulder`` (1: none)."""
        return 1.0

    def apply_exposure(self, gamma: Tensor, exposure, illum_ref: Tensor, log_ref: Optional[Tensor] = None) -> Tensor:
        """g after the user's exposure factor X > 0 (``--exposure``, the viewer's slider; < 1 brighter): g·X, a
        gamma scaled. ``exposure``: a float or a tensor; ``log_ref``: log lin(L_ref) if the caller has it."""
        return gamma * exposure

    def fusable(self) -> bool:
        """Whether a frame of this tone can be toned by :attr:`fused_kernel`."""
        return self.fused_kernel is not None

    def fused_gain(self, illum_ref: Tensor, gamma: Tensor, log_ref: Optional[Tensor] = None) -> Tensor:
        """The ``gain`` argument of :attr:`fused_kernel` for g (flattened, [1] or [3])."""
        raise NotImplementedError(f"tone {self.name!r} has no fused kernel")

    def fused(self, image: Tensor, gain: Tensor, shoulder: float) -> Tensor:
        """S_enh [H,W,3] of a rasterized [H,W,6] frame (R̂ then L̂) through :attr:`fused_kernel`, forward only."""
        from retinexgs.render._backend import kernels  # the compiled module, loaded on first use
        return getattr(kernels(), self.fused_kernel)(image, gain, shoulder)

    def describe(self, gamma: Tensor, illum_ref: Tensor, shoulder: float, balanced: bool) -> str:
        """The PLY comment's formula of the baked colour with its numbers (g [C] float64 on the CPU, L_ref);
        ``balanced``: a white balance W is applied."""
        form = f"srgb(W*lin({self.formula}))" if balanced else self.formula
        return f"colour: enhanced {form}, L_ref = {float(illum_ref):.4f}, g = ({_numbers(gamma, '.4f')})"


def _numbers(x: Tensor, spec: str) -> str:
    return ", ".join(format(v, spec) for v in torch.as_tensor(x).reshape(-1).tolist())


# name -> the tone object (tones hold no state: the model's numbers are passed to every call).
TONES: Dict[str, Tone] = {}

T = TypeVar("T", bound=Type[Tone])


def register(cls: T) -> T:
    """Class decorator: make ``cls`` selectable as ``model.enhancement.tone: <cls.name>``. A second class under a
    name already taken is refused (two tones would silently share one config value); the same class again (a
    module reloaded) replaces its entry."""
    name = getattr(cls, "name", "")
    if not isinstance(name, str) or not name:
        raise ValueError(f"tone class {cls.__name__} needs a non-empty string `name`")
    held = TONES.get(name)
    if held is not None and (type(held).__module__, type(held).__qualname__) != (cls.__module__, cls.__qualname__):
        raise ValueError(f"tone {name!r} is already registered by {type(held).__module__}.{type(held).__qualname__}")
    TONES[name] = cls()
    return cls


def get_tone(tone: Union[str, Tone]) -> Tone:
    """The registered tone of a name (a :class:`Tone` is returned as is); ValueError naming the choices."""
    if isinstance(tone, Tone):
        return tone
    found = TONES.get(tone) if isinstance(tone, str) else None
    if found is None:
        raise ValueError(f"tone must be one of {', '.join(TONES)}, got {tone!r}")
    return found


def config_problem(enh: "Enhancement") -> Optional[str]:
    """What is wrong with a ``model.enhancement`` section's tone, in one line, or None: an unregistered name, a
    tone that needs ``ref_quantile`` without one. The config loader
    checks it (the schema sits below the model and cannot see the registry)."""
    if enh.tone not in TONES:
        return f"model.enhancement.tone must be one of {', '.join(TONES)}, got {enh.tone!r}"
    tone = TONES[enh.tone]
    if tone.needs_reference and enh.ref_quantile is None:
        # e.g. k = lin(L_ref)^(-1/g): with L_ref = 1 the gain would be 1 for every g
        others = " or ".join(repr(n) for n, t in TONES.items() if not t.needs_reference)
        return (f"model.enhancement.tone {tone.name!r} needs a ref_quantile (it is set relative to the scene's full "
                f"light L_ref); null is only valid with {others}")
    return None


