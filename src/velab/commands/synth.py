"""``velab synth``: a synthetic water-hammer run of a known material (the paper's experiment with
--friction linear --valve imposed)."""

from __future__ import annotations

import argparse
import logging

from velab import bounds
from velab.commands.common import bound_float, float_range, int_range, prepare_output
from velab.errors import DataError, SafetyError

log = logging.getLogger("velab.synth")

# The work is bounded before anything is allocated: samples = rate x (pretrigger + duration).
# 5 million samples (50 kHz x 100 s) take about 1.5 GB at the model's peak.
MAX_SAMPLES = 5_000_000
# The sampling rate must resolve the manoeuvre: at least twice the frequency above which the valve
# flow's spectrum is negligible (velab.synth.flow_band_hz: the imposed sigmoid's band is 31 Hz for
# beta = 32 1/s; the orifice law on a butterfly closes the flow about twice as fast).
NYQUIST_FACTOR = 2.0


def register(sub) -> None:
    p = sub.add_parser(
        "synth",
        help="synthesise a run of a known material (the rig's valve and friction; --friction linear --valve "
        "imposed: the paper's experiment)",
        description="Synthesise the head at the valve for a pipe-wall material on a rig, add white noise, and "
        "write a run file (a rig with several [[transducers]]: one head channel per transducer, 'head' for the "
        "valve's and 'head_NAME' for the others, each with its own noise). The rig's valve and friction laws make the data (the reference rigs: the actuator "
        "moves the butterfly valve along the sigmoid in position and the flow obeys the orifice law, with "
        "quadratic Darcy-Weisbach friction, through the time-domain model); --friction linear --valve imposed "
        "gives the paper's synthetic experiment (the sigmoid is the flow; the frequency-domain model). "
        "Materials: built-in names (A, B, elastic, hdpe_s1) "
        "or a TOML file with wave_speed_m_s and [[kelvin_voigt]] elements (E_pa + eta_pa_s or J_per_pa + tau_s). "
        f"The rate must resolve the manoeuvre (at least {NYQUIST_FACTOR:g} x its band) and rate x (pretrigger + "
        f"duration) is at most {MAX_SAMPLES:,} samples.",
    )
    p.add_argument("--material", default="A", help="material name or TOML file (default: A)")
    p.add_argument("--rig", default="perugia", help="rig name or TOML file (default: perugia)")
    p.add_argument("--noise", type=float_range(0, 100, units="m"), default=None,
                   help="noise standard deviation, m, 0..100 (default: the paper's, 0.1 m)")
    p.add_argument("--seed", type=int_range(0, 2**63 - 1), default=None, help="noise seed (default: the paper's, 2018)")
    p.add_argument("--rate", type=bound_float(bounds.SAMPLE_RATE_HZ), default=1000.0,
                   help="sampling rate, Hz (default 1000)")
    p.add_argument("--duration", type=float_range(0, 3600, lo_open=True, units="s"), default=20.0,
                   help="record after the trigger, s (default 20)")
    p.add_argument("--pretrigger", type=float_range(0, 600, units="s"), default=1.0,
                   help="record before the trigger, s (default 1)")
    p.add_argument("--beta", type=bound_float(bounds.BETA_PER_S),
                   help="sigmoid beta, 1/s (default: the rig's)")
    p.add_argument("--gamma", type=bound_float(bounds.GAMMA), help="sigmoid gamma, -100..0 (default: the rig's)")
    # choices checked in run(): the law names live in velab.friction, which needs numpy (--help stays light)
    p.add_argument("--friction", metavar="LAW",
                   help="steady friction: quadratic (Darcy-Weisbach), linear (the paper's tangent), none "
                   "(default: the rig's)")
    p.add_argument("--friction-unsteady", metavar="LAW",
                   help="unsteady friction: none, vardy-brown (weighting function), brunone (default: the rig's)")
    p.add_argument("--valve", choices=("orifice", "imposed"),
                   help="the valve: orifice (the sigmoid is the valve's position, the flow obeys the orifice law "
                   "of the rig's [valve]), imposed (the sigmoid is the flow, the paper's model) (default: the rig's)")
    p.add_argument("-o", "--output", required=True, help="run file to write (.h5)")
    p.add_argument("--force", action="store_true", help="replace an existing output file")
    p.add_argument("--title", default=None, help="run title")
    p.set_defaults(func=run)


def check_work(rate_hz: float, duration_s: float, pretrigger_s: float) -> int:
    """Samples the run will have; refused above MAX_SAMPLES or below two per second of record."""
    n = rate_hz * (duration_s + pretrigger_s)
    if n > MAX_SAMPLES:
        raise DataError(f"--rate {rate_hz:g} Hz x {duration_s + pretrigger_s:g} s = {n:,.0f} samples, more than "
                        f"the {MAX_SAMPLES:,} a synthetic run may have (lower --rate or --duration)")
    return int(round(n))


def refuse_cavitation(rig) -> None:
    """No synthetic record of a rig whose downsurge reaches the vapour-pressure head: no model of velab holds
    there (column separation, velab.cavitation). The undamped Joukowsky downsurge, no margin (exit 3)."""
    from velab.cavitation import predict_downsurge

    down = predict_downsurge(rig, surge_margin=0.0)
    if not down.allowed:
        raise SafetyError(f"synthetic run refused: rig {rig.name}: "
                          + down.message.removeprefix("manoeuvre refused: "))


def run(args: argparse.Namespace) -> int:
    check_work(args.rate, args.duration, args.pretrigger)
    out = prepare_output(args.output, args.force)

    from velab.config import load_material, load_rig
    from velab.rig import Manoeuvre
    from velab.friction import STEADY_LAWS, UNSTEADY_LAWS
    from velab.synth import (PAPER_NOISE_STD_M, PAPER_SEED, SynthSettings, flow_band_hz, head_model, synthesise,
                             with_valve_law)

    for option, value, laws in (("--friction", args.friction, STEADY_LAWS),
                                ("--friction-unsteady", args.friction_unsteady, UNSTEADY_LAWS)):
        if value is not None and value not in laws:
            raise DataError(f"{option} {value!r}: choose from {', '.join(laws)}")

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
    if args.valve is not None:
        rig = with_valve_law(rig, args.valve)
    problem = bounds.rig_problem(rig)  # the options' rig, by the rule its file was read with (velab.bounds)
    if problem:
        raise DataError(f"rig {rig.name} with these options: {problem[0]}: {problem[1]}")
    work = bounds.work_problem(rig, args.duration + args.pretrigger)
    if work:
        raise DataError(f"--duration {args.duration:g} s: {work}")
    refuse_cavitation(rig)
    min_rate = NYQUIST_FACTOR * flow_band_hz(rig)
    if args.rate < min_rate:
        raise DataError(f"--rate {args.rate:g} Hz cannot resolve the manoeuvre (beta {rig.manoeuvre.beta_per_s:g} 1/s: "
                        f"band {min_rate / NYQUIST_FACTOR:.3g} Hz); use at least {min_rate:.3g} Hz")
    material = load_material(args.material)
    s = SynthSettings(noise_std_m=PAPER_NOISE_STD_M if args.noise is None else args.noise,
                      seed=PAPER_SEED if args.seed is None else args.seed, sample_rate_hz=args.rate,
                      duration_s=args.duration, pretrigger_s=args.pretrigger)
    log.info("synthesising %s on %s: %g Hz, %g s + %g s", material.name, rig.name, s.sample_rate_hz,
             s.pretrigger_s, s.duration_s)
    t, head, flow, position = synthesise(rig, material, s)
    import numpy as np

    if not (np.isfinite(head).all() and np.isfinite(flow).all()):
        raise DataError(f"the model gives non-finite heads for material {material.name} on {rig.name} with "
                        f"these settings (beta {rig.manoeuvre.beta_per_s:g}, gamma {rig.manoeuvre.gamma:g}); "
                        f"nothing written")
    from velab.runfiles import write_run

    model = head_model(rig)
    friction = {"friction": rig.friction, "friction_unsteady": rig.friction_unsteady, "valve": rig.valve.law,
                "head_model": model}
    # the flow the model let through, and with the orifice law the position that made it
    channels = {"flow": (flow, "m^3/s")}
    if position is not None:
        channels["valve_position"] = (position, "%")
    if len(rig.sections) > 1:  # one head channel per transducer of the rig, named after it
        from velab.synth import synthesise_sections

        by_name = {x.name: x for x in rig.sections}
        for name, h in synthesise_sections(rig, material, s).items():
            channels[rig.section_channel(by_name[name])] = (h, "m")
    title = args.title or f"synthetic {material.model_name} material {material.name} on {rig.name}"
    write_run(
        out, rig, t, head, status="synthetic", title=title, material=material, noise_std_m=s.noise_std_m,
        extra_channels=channels, sample_rate_hz=s.sample_rate_hz, overwrite=args.force,
        source={"kind": "synth", "material": str(args.material), "rig": str(args.rig), **s.__dict__, **friction},
        settings={"synth": {**s.__dict__, **friction}, "rig": str(args.rig), "material": str(args.material)},
    )
    sections = "" if len(rig.sections) < 2 else "; sections: " + ", ".join(
        f"{x.name} at {x.position_m:g} m ({rig.section_channel(x)})" for x in rig.sections)
    print(f"wrote {out}: {material.model_name} material {material.name}, {t.size} samples at {s.sample_rate_hz:g} Hz, "
          f"noise {s.noise_std_m:g} m (seed {s.seed}); valve: {rig.valve.describe()}; friction "
          f"{rig.friction_description} ({model}){sections}")
    return 0
