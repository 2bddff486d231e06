"""``velab synth``: the paper's synthetic water-hammer run, written as a run file."""

from __future__ import annotations

import argparse

from velab.commands.common import non_negative_float, positive_float, prepare_output
from velab.config import Manoeuvre, load_material, load_rig
from velab.runfile import write_run
from velab.friction import STEADY_LAWS, UNSTEADY_LAWS
from velab.synth import PAPER_NOISE_STD_M, PAPER_SEED, SynthSettings, friction_is_linear, synthesise


def register(sub) -> None:
    p = sub.add_parser(
        "synth",
        help="synthesise a run of a known material (the rig's friction; --friction linear: the paper's experiment)",
        description="Synthesise the head at the valve for a pipe-wall material on a rig, add white noise, and "
        "write a run file. The rig's friction laws make the data (the reference rigs: quadratic Darcy-Weisbach, "
        "through the time-domain model); --friction linear gives the paper's synthetic experiment (the "
        "frequency-domain model). Materials: built-in names (A, B, elastic, hdpe_s1) "
        "or a TOML file with wave_speed_m_s and [[kelvin_voigt]] elements (E_pa + eta_pa_s or J_per_pa + tau_s).",
    )
    p.add_argument("--material", default="A", help="material name or TOML file (default: A)")
    p.add_argument("--rig", default="perugia", help="rig name or TOML file (default: perugia)")
    p.add_argument("--noise", type=non_negative_float, default=PAPER_NOISE_STD_M,
                   help=f"noise standard deviation, m (default {PAPER_NOISE_STD_M})")
    p.add_argument("--seed", type=int, default=PAPER_SEED, help=f"noise seed (default {PAPER_SEED})")
    p.add_argument("--rate", type=positive_float, default=1000.0, help="sampling rate, Hz (default 1000)")
    p.add_argument("--duration", type=positive_float, default=20.0, help="record after the trigger, s (default 20)")
    p.add_argument("--pretrigger", type=non_negative_float, default=1.0, help="record before the trigger, s (default 1)")
    p.add_argument("--beta", type=positive_float, help="sigmoid beta, 1/s (default: the rig's)")
    p.add_argument("--gamma", type=float, help="sigmoid gamma (default: the rig's)")
    p.add_argument("--friction", choices=STEADY_LAWS,
                   help="steady friction: quadratic (Darcy-Weisbach), linear (the paper's tangent), none "
                   "(default: the rig's)")
    p.add_argument("--friction-unsteady", choices=UNSTEADY_LAWS,
                   help="unsteady friction: none, vardy-brown (weighting function), brunone (default: the rig's)")
    p.add_argument("-o", "--output", required=True, help="run file to write (.h5)")
    p.add_argument("--force", action="store_true", help="replace an existing output file")
    p.add_argument("--title", default=None, help="run title")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    rig = load_rig(args.rig)
    if args.beta is not None or args.gamma is not None:
        rig = rig.with_changes(manoeuvre=Manoeuvre(
            beta_per_s=args.beta if args.beta is not None else rig.manoeuvre.beta_per_s,
            gamma=args.gamma if args.gamma is not None else rig.manoeuvre.gamma,
        ))
    if args.friction is not None:
        rig = rig.with_changes(friction=args.friction)
    if args.friction_unsteady is not None:
        rig = rig.with_changes(friction_unsteady=args.friction_unsteady)
    material = load_material(args.material)
    out = prepare_output(args.output, args.force)
    s = SynthSettings(noise_std_m=args.noise, seed=args.seed, sample_rate_hz=args.rate,
                      duration_s=args.duration, pretrigger_s=args.pretrigger)
    t, head, flow = synthesise(rig, material, s)
    model = "frequency-domain model" if friction_is_linear(rig) else "time-domain model (MOC)"
    friction = {"friction": rig.friction, "friction_unsteady": rig.friction_unsteady, "head_model": model}
    title = args.title or f"synthetic {material.model_name} material {material.name} on {rig.name}"
    write_run(
        out, rig, t, head, status="synthetic", title=title, material=material, noise_std_m=s.noise_std_m,
        extra_channels={"flow": (flow, "m^3/s")}, sample_rate_hz=s.sample_rate_hz, overwrite=args.force,
        source={"kind": "synth", "material": str(args.material), "rig": str(args.rig), **s.__dict__, **friction},
        settings={"synth": {**s.__dict__, **friction}, "rig": str(args.rig), "material": str(args.material)},
    )
    print(f"wrote {out}: {material.model_name} material {material.name}, {t.size} samples at {s.sample_rate_hz:g} Hz, "
          f"noise {s.noise_std_m:g} m (seed {s.seed}); friction {rig.friction_description} ({model})")
    return 0
