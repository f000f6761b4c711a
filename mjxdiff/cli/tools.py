"""The commands of the other uses (:mod:`mjxdiff.tools`): ``fuzz``, ``bench``, ``policy``,
``coverage``, ``grad``, ``versions``, ``shrink``, ``scale``: each a function adding its parser
and one running it."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from pathlib import Path

from mjxdiff.errors import one_line
from mjxdiff.input.options import positive, seconds
from mjxdiff.cli.args import DESCRIPTIONS, selected, shared


_BENCH_DEFAULT = ("pendulum", "cartpole", "ant")


_VERSIONS_EPILOG = """\
examples:
  python -m mjxdiff versions 3.9.0/0.7.2 3.17.0 --quick           # a playground pin against the newest
  python -m mjxdiff versions 3.3.5/0.7.0 3.9.0/0.7.2 3.17.0 --scenarios pendulum humanoid
  python -m mjxdiff versions 3.12.0 3.17.0 --scenarios my_robot.toml --out upgrade-check
  python -m mjxdiff versions 3.17.0 3.17.0+core4.0.1 --quick   # the same MJX against C 4.0.0 and 4.0.1

The first run of a version installs it (a minute or two, about 1 GB per environment); later runs
reuse it while mjxdiff's requirements are unchanged."""


_BENCH_DESCRIPTION = """\
Measure both platforms on the same batch, horizon and cores: steps/s of MJX and
of MuJoCo C for several batch sizes (MJX's best batch size is model-specific),
their ratio, MJX compile seconds, peak memory and CPU utilisation of each side,
the speedup of splitting MJX's batch over host devices, and how much the
verification itself (noise floor, metrics, verdict) costs on top of the two
engines. Ends with plain-language recommendations. float64 throughout."""


_BENCH_EPILOG = """\
examples:
  python -m mjxdiff bench                         # pendulum, cartpole, ant
  python -m mjxdiff bench humanoid --batch 16 64  # one scenario, two batch sizes
  python -m mjxdiff bench ant --out bench-results --format json

steps/s counts member-steps (batch x steps) per wall second, best of --repeats
warm runs. MJX splits a batch over the host CPU devices (one per core) when each
gets at least 16 members; bench then adds a one-device comparison at the best
batch. MJXDIFF_DEVICES=N (in the environment) sets the number of devices."""


def fuzz_parser(sub) -> argparse.ArgumentParser:
    fz = sub.add_parser("fuzz", help="hunt for divergences with generated models (Hypothesis), shrink what is found",
                        description=DESCRIPTIONS["fuzz"],
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    fz.add_argument("--max-examples", type=positive, default=300,
                    help="most generated models (structures) to try (default 300); each is judged on "
                         "64 variants of its parameters, initial state and controls, compiled once")
    shared(fz, "seed", seed="Hypothesis seed (default 0)")
    fz.add_argument("--budget", type=float, default=None, metavar="SECONDS",
                    help="seconds of generation (default 60); shrinking a find may take longer")
    shared(fz, "out", out="save the reproducer and the example database under DIR")
    fz.add_argument("--include-known", action="store_true",
                    help="also generate features with known, documented C/MJX divergences "
                         "(connect/weld, RK4/implicitfast, box and mesh geoms, tendon wrap sidesites) and report "
                         "the contact differences known by their signature (plane-cylinder far cap, capsule contact "
                         "frames)")
    shared(fz, "cache_dir")
    return fz


def bench_parser(sub) -> argparse.ArgumentParser:
    bn = sub.add_parser("bench", help="measure MJX and MuJoCo C throughput, compile time and memory per scenario",
                        description=_BENCH_DESCRIPTION, epilog=_BENCH_EPILOG,
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    shared(bn, "scenarios", scenarios=
            f"bundled scenario name, scenario .toml or MJCF .xml (default: {' '.join(_BENCH_DEFAULT)}, "
            "a small, a medium and an ant-class model)")
    bn.add_argument("--batch", type=positive, nargs="+", metavar="B",
                    help="batch sizes of the throughput curve (default 8 32 128)")
    bn.add_argument("--steps", type=positive, default=200, help="steps per rollout (default 200)")
    bn.add_argument("--repeats", type=positive, default=2, help="warm runs per measurement, best kept (default 2)")
    shared(bn, "seed", "out", "format", "cache_dir", out="write DIR/bench.json (versions, machine, every number)")
    return bn


def policy_parser(sub) -> argparse.ArgumentParser:
    po = sub.add_parser("policy", help="run a policy in closed loop on MJX and on MuJoCo C and compare episodes",
                        description=DESCRIPTIONS["policy"])
    po.add_argument("target", metavar="MODEL_OR_ENV", nargs="?",
                    help="a brax environment name (MJX backend, e.g. inverted_pendulum), a bundled scenario, "
                         "a scenario .toml or an MJCF .xml (observations qpos, qvel, sensordata; actions in "
                         "[-1, 1] onto ctrlrange; no reward: compare states)")
    po.add_argument("--replay", metavar="FILE",
                    help="re-run the one episode a failing run saved (DIR/policy-reproducer.json, written "
                         "with --out): same target, policy, seed and keys")
    po.add_argument("--policy", metavar="SPEC",
                    help="a brax PPO checkpoint directory, PARAMS_FILE::module:factory (brax.io.model.save_params "
                         "and a make_ppo_networks-like factory), or module:function (a policy(obs, key), or a "
                         "factory of the observation and action sizes returning one)")
    po.add_argument("--episodes", type=positive, default=16, help="episodes per engine (default 16)")
    po.add_argument("--steps", type=positive, default=200, help="control steps per episode (default 200)")
    po.add_argument("--n-frames", type=positive, default=1,
                    help="substeps per control step for an MJCF (brax environments bring their own)")
    shared(po, "seed", "out", "format", seed="seed of resets and policy keys (default 0)",
            out="write DIR/policy-report.json")
    return po


def coverage_parser(sub) -> argparse.ArgumentParser:
    cv = sub.add_parser("coverage", help="measure which MJX code and which model parameters the scenarios exercise",
                        description=DESCRIPTIONS["coverage"])
    shared(cv, "scenarios", "seed", "out", "format", out="write DIR/coverage.json")
    return cv


def grad_parser(sub) -> argparse.ArgumentParser:
    gr = sub.add_parser("grad", help="compare MJX's one-step Jacobians (jax.jacfwd) with C's finite differences",
                        description=DESCRIPTIONS["grad"])
    shared(gr, "scenarios", scenarios=
            "bundled scenario name, scenario .toml or MJCF .xml (default: the smooth ones: pendulum, "
            "double_pendulum, cartpole, actuators, gravcomp_arm)")
    gr.add_argument("--states", type=positive, default=8, help="states sampled per scenario (default 8)")
    shared(gr, "seed", "out", "format", out="write DIR/grad-report.json, DIR/grad-report.html (a heat map of each "
            "failing scenario's worst state) and, per failing scenario, its worst state as "
            "DIR/reproducers/NAME-grad-stateI.json for 'mjxdiff replay'")
    return gr


def versions_parser(sub) -> argparse.ArgumentParser:
    ve = sub.add_parser("versions", help="run the same sweep on several MJX releases and tabulate the verdicts",
                        description=DESCRIPTIONS["versions"], epilog=_VERSIONS_EPILOG,
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    ve.add_argument("targets", nargs="+", metavar="MJX[/JAX][+coreC]", type=_target,
                    help="an MJX release (3.9.0; its MuJoCo is installed with it, 4.0 for MJX 3.17), optionally with "
                         "the JAX to pair it with (3.9.0/0.7.2; default: the newest pip finds within mjxdiff's range) "
                         "and the MuJoCo C to judge it against (3.17.0+core4.0.1: mujoco-core 4.0.1 over the pinned "
                         "4.0.0, MJX unchanged, to see whether C is the one that moved)")
    ve.add_argument("--scenarios", nargs="+", default=[], metavar="SCENARIO",
                    help="bundled scenario names, scenario .toml or MJCF .xml files to sweep on every version "
                         "(default: every bundled scenario)")
    ve.add_argument("--quick", action="store_true", help="sweep --quick on every version")
    shared(ve, "seed", "out", out="write OUT/versions.json, each version's report under OUT/<version>/ and their runs "
                            "to the history OUT/history (default mjxdiff-versions)")
    ve.add_argument("--envs", metavar="DIR", help="where the environments are kept and reused (default "
                                                  "$XDG_CACHE_HOME/mjxdiff/versions or ~/.cache/mjxdiff/versions)")
    ve.add_argument("--extras", nargs="*", default=[], metavar="EXTRA",
                    help="mjxdiff extras installed in every environment too (test: to run the suite there)")
    shared(ve, "format")
    return ve


def _target(text: str):
    from mjxdiff.tools.versions import parse_target

    try:
        return parse_target(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def cmd_versions(args: argparse.Namespace) -> int:
    from mjxdiff.tools import versions

    scenarios = [str(Path(x).resolve()) if Path(x).suffix else x for x in args.scenarios]  # files: for the child
    sweep_args = [*scenarios, "--seed", str(args.seed), *(["--quick"] if args.quick else [])]
    cache = Path(args.envs) if args.envs else Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / \
        "mjxdiff" / "versions"
    say = (lambda line: print(line, file=sys.stderr)) if args.format == "json" else print
    doc = versions.run(args.targets, sweep_args, Path(args.out or "mjxdiff-versions"), cache, args.extras, say)
    if args.format == "json":
        print(json.dumps(doc, indent=2))
    else:
        print(versions.format_table(doc["table"]))
    cells = [c for row in doc["table"]["rows"].values() for c in row.values()]
    return 1 if doc["table"]["errors"] or any(c["status"] in ("fail", "error") and not c["known"] for c in cells) else 0


def shrink_parser(sub) -> argparse.ArgumentParser:
    sh = sub.add_parser("shrink", help="shrink a diverging model to a minimal MJCF with the same divergence",
                        description=DESCRIPTIONS["shrink"])
    sh.add_argument("model", metavar="MODEL", help="an MJCF file, or a reproducer .json ('sweep --out' writes them)")
    sh.add_argument("--out", metavar="DIR", default="mjxdiff-out/shrink", help="where to write (default %(default)s)")
    sh.add_argument("--bundle", action="store_true",
                    help="write a bug bundle: repro.py, signature.json and README.md beside the model")
    sh.add_argument("--keyframe", type=int, metavar="K", help="start C's rollout from keyframe K (default qpos0)")
    sh.add_argument("--steps", type=positive, default=200, metavar="N",
                    help="states of C's rollout searched for the divergence (default 200)")
    sh.add_argument("--budget", type=seconds, default=600.0, metavar="SECONDS",
                    help="stop shrinking after this long with the best so far (default 600)")
    return sh


def shrink_input(path: str, keyframe: int | None, steps: int):
    """(spec, state, signature, step, source directory) of a model file or a reproducer."""
    import mujoco
    import numpy as np

    from mjxdiff.output import reproducer
    from mjxdiff.tools import shrink

    ctrl = None
    if path.endswith(".json"):
        rep = reproducer.load(path)
        spec = shrink.named(mujoco.MjSpec.from_string(rep.model_xml))
        m = spec.compile()
        controls = np.asarray(rep.inputs.ctrl[0])
        ctrl = (lambda k: controls[min(k, len(controls) - 1)]) if controls.size else None
        start = (rep.inputs.qpos[0], rep.inputs.qvel[0], rep.inputs.act[0])
        source = None
    else:
        spec = shrink.named(mujoco.MjSpec.from_file(path))
        m, start, source = spec.compile(), None, Path(path).resolve().parent
    if keyframe is not None and not 0 <= keyframe < m.nkey:
        raise ValueError(f"--keyframe {keyframe}: the model has {m.nkey} keyframes")
    found = shrink.find_state(m, steps, keyframe, ctrl, start)
    return spec, found, source


def cmd_shrink(args: argparse.Namespace) -> int:
    from mjxdiff.tools import bundle, shrink
    from mjxdiff.engine import engines
    from mjxdiff.input.scenario import ScenarioError

    engines.configure_jax("float64")
    try:
        spec, found, source = shrink_input(args.model, args.keyframe, args.steps)
    except NotImplementedError as e:
        print(f"mjxdiff shrink: error: unsupported by MJX, nothing to compare: {one_line(e)}", file=sys.stderr)
        return 2
    except (ScenarioError, ValueError, OSError) as e:
        print(f"mjxdiff shrink: error: {one_line(e)}", file=sys.stderr)
        return 2
    if found is None:
        print(f"mjxdiff shrink: error: no divergence in the first {args.steps} states of C's rollout: nothing to "
              "shrink (a sweep's reproducer starts from the failing member's state)", file=sys.stderr)
        return 2
    state, signature, step = found
    print(f"shrink: {signature.describe()} at step {step}", file=sys.stderr)
    shrunk = shrink.shrink(spec, state, signature, args.budget, lambda line: print(line, file=sys.stderr),
                           steps_before=step + 1)
    out = Path(args.out)
    if args.bundle:
        bundle.write(shrunk, out, source, origin=args.model)
    else:
        out.mkdir(parents=True, exist_ok=True)
        bundle.write_model(shrunk, out, source)
    print(f"{signature.describe()}\nbefore: {shrunk.before}\nafter:  {shrunk.after}\n"
          f"{shrunk.candidates} candidates, {shrunk.compiles} XLA compiles, {shrunk.seconds:.0f} s"
          + ("" if shrunk.complete else " (stopped early: the best so far)") + f"\nwritten to {out}")
    return 0


def scale_parser(sub) -> argparse.ArgumentParser:
    sc = sub.add_parser("scale", help="predict a sweep's wall time on 1-64 nodes from its journal",
                        description=DESCRIPTIONS["scale"])
    sc.add_argument("dirs", nargs="+", metavar="DIR", help="--out directories whose journal.jsonl measured the units")
    sc.add_argument("--nodes", type=positive, nargs="+", metavar="N", help="node counts (default 1 2 4 ... 64)")
    sc.add_argument("--cpus-per-node", type=positive, default=2, metavar="C", help="CPUs of a node (default 2)")
    sc.add_argument("--cpus-per-scenario", type=positive, default=1, metavar="K",
                    help="CPUs each unit's task asks for (default 1)")
    sc.add_argument("--fixed", type=float, default=0.0, metavar="SECONDS",
                    help="seconds the run costs once: starting or joining Ray, the workers' imports (default 0)")
    sc.add_argument("--per-task", type=float, default=0.0, metavar="SECONDS",
                    help="seconds each unit costs on top of its own (default 0)")
    shared(sc, "format")
    return sc


def cmd_scale(args: argparse.Namespace) -> int:
    from mjxdiff.runner import journal, scaling

    units = {}
    for d in args.dirs:
        for r in journal.read(Path(d) / journal.FILE).units:
            units[r["key"]] = (r["unit"], float(r.get("seconds") or 0.0))  # a unit recorded twice: the later
    if not units:
        print(f"mjxdiff: error: no finished unit in {', '.join(args.dirs)} (a sweep run with --out DIR journals "
              "them)", file=sys.stderr)
        return 2
    predictions = scaling.predict(list(units.values()), args.nodes or scaling.NODES,
                                  max(1, args.cpus_per_node // args.cpus_per_scenario), args.fixed, args.per_task)
    if args.format == "json":
        print(json.dumps([dataclasses.asdict(p) for p in predictions], indent=2))
    else:
        print(f"{len(units)} units, {sum(s for _, s in units.values()):.1f} s of work")
        print(scaling.format_table(predictions))
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from mjxdiff.tools import bench
    from mjxdiff.engine import engines
    from mjxdiff.output import report
    from mjxdiff.input.scenario import ScenarioError, load_scenario

    engines.configure_jax("float64", args.cache_dir)
    try:
        scenarios = [load_scenario(ref) for ref in args.scenarios or _BENCH_DEFAULT]
    except ScenarioError as e:
        print(f"mjxdiff: error: {e}", file=sys.stderr)
        return 2
    say = (lambda text: print(f"... {text}", file=sys.stderr, flush=True)) if sys.stderr.isatty() else None
    results = []
    for scenario in scenarios:
        try:
            results.append(bench.bench_scenario(scenario, args.batch or bench.DEFAULT_BATCHES, args.steps,
                                                args.seed, args.repeats, say))
        except engines.UnsupportedError as e:
            print(f"mjxdiff: {scenario.name}: skipped, MJX does not support: {e.feature}", file=sys.stderr)
            continue
        if args.format == "text":
            print(bench.format_text(results[-1:]), flush=True)
    doc = report.envelope("bench", dict(scenarios=args.scenarios, batch=args.batch, steps=args.steps, seed=args.seed,
                                        repeats=args.repeats), steps=args.steps, scenarios=results)
    if args.out:
        path = report.write_report(args.out, doc, "bench.json")
        print(f"bench written to {path}", file=sys.stderr)
    if args.format == "json":
        print(json.dumps(doc, indent=2))
    return 0 if results else 1


def cmd_fuzz(args: argparse.Namespace) -> int:
    from mjxdiff.engine import engines
    from mjxdiff.output import report
    from mjxdiff.tools.fuzz import DEFAULT_BUDGET, fuzz

    engines.configure_jax("float64", args.cache_dir)
    budget = DEFAULT_BUDGET if args.budget is None else args.budget
    if budget <= 0:
        print("mjxdiff: error: --budget must be positive (see 'mjxdiff fuzz --help')", file=sys.stderr)
        return 2
    result = fuzz(max_examples=args.max_examples, seed=args.seed, budget=budget, out=args.out,
                  include_known=args.include_known, progress=sys.stderr.isatty())
    written = None
    if args.out:
        doc = report.envelope("fuzz", dict(max_examples=args.max_examples, seed=args.seed, budget=budget,
                                           include_known=args.include_known),
                   examples=result.examples, structures=result.structures, seconds=result.seconds,
                   **result.rates(), failure=result.failure,
                   harness_error=result.harness_error, traceback=result.harness_traceback,
                   harness_example=result.harness_example, interactions=result.interactions,
                   set_aside=result.set_aside)
        written = report.write_report(args.out, doc, "fuzz-report.json")
    if result.harness_error is not None:
        # the run proves nothing: not "no divergence", whatever was tried before
        print(f"mjxdiff: error: fuzz harness failed: {result.harness_error}", file=sys.stderr)
        assert result.harness_traceback is not None  # recorded with the harness error
        print(result.harness_traceback.rstrip("\n"), file=sys.stderr)
        if written:
            print(f"fuzz report written to {written}", file=sys.stderr)
        if result.failure is not None:
            print(f"(a divergence was found before the harness failed: {result.failure['message']})")
        return 2
    if written:
        print(f"fuzz report written to {written}", file=sys.stderr)
    rates = result.rates()
    tried = (f"{result.examples} examples ({result.structures} generated models x "
             f"{result.examples // max(1, result.structures)} variants; {rates['examples_per_minute']:.0f} examples, "
             f"{rates['structures_per_minute']:.1f} models per minute)")
    notes = []  # printed after the verdict
    if result.set_aside:  # models judged that count neither way, each with why
        notes.append("set aside, neither a pass nor a find: " + ", ".join(
            f"{n} ({why})" for why, n in sorted(result.set_aside.items())))
    if result.interactions:
        from mjxdiff.tools import interactions
        line = interactions.format_text(result.interactions, "interaction pairs generated", "fuzz-report.json")
        notes.append(f"{line.splitlines()[0]}; {result.interactions['pairs_per_minute']:.0f} per minute")
    if result.failure is None:
        print(f"no divergence in {tried}, {result.seconds:.0f} s")
        if notes:
            print("\n".join(notes))
        return 0
    f = result.failure
    print(f"DIVERGENCE ({f['status']}) after {tried}, {result.seconds:.0f} s: {f['message']}")
    print(f"shrunk to {f['nbody']} bodies, {f['ngeom']} geoms; features: {', '.join(f['features']) or 'none'}")
    if f["reproducer"]:
        print(f"reproducer: {f['reproducer']} (python -m mjxdiff replay {f['reproducer']})")
    print(f["xml"])
    if notes:
        print("\n".join(notes))
    return 1


def cmd_policy(args: argparse.Namespace) -> int:
    from mjxdiff.tools import closedloop
    from mjxdiff.engine import engines
    from mjxdiff.output import report

    only = None
    if args.replay:
        try:
            saved = json.loads(Path(args.replay).read_text())
            if saved.get("kind", "policy-reproducer") != "policy-reproducer":
                raise ValueError(f"a {saved['kind']} output")
            args.target, args.policy, only = saved["target"], saved["policy"], [int(saved["episode"])]
            config = saved["config"] if "kind" in saved else saved  # before the envelope: at the top level
            args.episodes, args.steps, args.seed, args.n_frames = (int(config[k]) for k in
                                                                   ("episodes", "steps", "seed", "n_frames"))
        except (OSError, ValueError, KeyError, TypeError) as e:
            print(f"mjxdiff policy: {args.replay}: not a policy reproducer ({one_line(e)})", file=sys.stderr)
            return 2
    if not args.target or not args.policy:
        print("mjxdiff policy: give MODEL_OR_ENV and --policy SPEC, or --replay FILE", file=sys.stderr)
        return 2
    engines.configure_jax("float64", None)
    try:
        env = closedloop.resolve_env(args.target, args.n_frames)
        policy = closedloop.load_policy(args.policy, env)
    except closedloop.PolicyError as e:
        print(f"mjxdiff policy: {e}", file=sys.stderr)
        return 2
    comparison = closedloop.run(env, policy, args.episodes, args.steps, args.seed, only=only)
    n_frames = int(env._n_frames)  # noqa: SLF001 - brax's substeps per control step
    result = closedloop.judge(closedloop.c_model(env), comparison, seed=args.seed, n_frames=n_frames)
    config = dict(episodes=args.episodes, steps=args.steps, seed=args.seed, n_frames=args.n_frames)
    doc = report.envelope("policy", dict(config, only=only), target=args.target, policy=args.policy, **result)
    if args.out:
        path = report.write_report(args.out, doc, "policy-report.json")
        print(f"report written to {path}", file=sys.stderr)
        if result["status"] == "fail" and only is None:
            worst = result["first_separation"]["episode"] if result["first_separation"] else result["worst_episode"]
            rep = report.envelope("policy-reproducer", config, target=args.target, policy=args.policy,
                                  episode=worst, message=result["message"])
            path = report.write_report(args.out, rep, "policy-reproducer.json")
            print(f"reproducer of episode {worst} written to {path} (mjxdiff policy --replay {path})",
                  file=sys.stderr)
    print(json.dumps(doc, indent=2) if args.format == "json" else f"{result['status'].upper():6} {args.target}  "
          f"{result['message']}")
    return 0 if result["status"] == "pass" else 1


def cmd_grad(args: argparse.Namespace) -> int:
    from mjxdiff.engine import engines
    from mjxdiff.tools import grad
    from mjxdiff.output import report

    scenarios = selected(args.scenarios or list(grad.SMOOTH))
    if scenarios is None:
        return 2
    engines.configure_jax("float64", None)
    rows = []
    for scenario in scenarios:
        rows.append(grad.check_scenario(scenario, args.states, args.seed,
                                        Path(args.out) / "reproducers" if args.out else None))
        if args.format == "text":
            print(grad.format_text(rows[-1:]), flush=True)
    doc = report.envelope("grad", dict(scenarios=args.scenarios, states=args.states, seed=args.seed, eps=grad.EPS),
                          scenarios=rows)
    if args.out:
        from mjxdiff.output import html_report

        print(f"report written to {report.write_report(args.out, doc, 'grad-report.json')} and "
              f"{html_report.write_grad(args.out, doc)}", file=sys.stderr)
    if args.format == "json":
        print(json.dumps(doc, indent=2))
    if any(r["status"] == "error" for r in rows):
        return 2
    return 1 if any(r["status"] == "fail" for r in rows) else 0


def cmd_coverage(args: argparse.Namespace) -> int:
    from mjxdiff.tools import coverage
    from mjxdiff.engine import engines
    from mjxdiff.output import report

    scenarios = selected(args.scenarios)
    if scenarios is None:
        return 2
    engines.configure_jax("float64", "")
    measured = coverage.measure(scenarios, args.seed)
    # "code" of the envelope names the MJX code tested: its line and branch coverage is "code_coverage"
    body = {("code_coverage" if k == "code" else k): v for k, v in measured.items()}
    doc = report.envelope("coverage", dict(scenarios=args.scenarios, seed=args.seed), **body)
    if args.out:
        path = report.write_report(args.out, doc, "coverage.json")
        print(f"coverage written to {path}", file=sys.stderr)
    print(json.dumps(doc, indent=2) if args.format == "json" else coverage.format_text(measured))
    return 0
