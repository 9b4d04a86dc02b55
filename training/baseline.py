"""Per-scene optimisation baseline (issue 6 part 2): fit each instance's parameters by CMA-ES
over re-simulated masks.

Unlike the learned estimator, the baseline is given the instance's geometry, initial state,
cameras and its TRUE family (so its Acc is 1 by construction). It searches the family's
sampled parameters in [0, 1]^d, each normalised over the family's own sampling range (log space
for E and yield stress), minimising the mean squared error between the re-simulated and the
observed mask videos of camera 0 (masks in [0, 1], all frames). That loss is exactly the MSE of
the re-simulation PSNR, so the fit's PSNR is psnr_from_mse(loss) of its best candidate.

Cost: each CMA-ES generation of `parallel` instances is ONE ad_sim.resimulate call of
parallel x popsize scenes (e.g. 16 x 16 = 256, the CUDA solver's sweet spot). Every instance has
its own CMA-ES random stream (from --seed and its episode id), and a scene's simulation on CPU
does not depend on its batch, so on CPU a fit does not depend on which instances it was batched with.
"""
from __future__ import annotations

import argparse
import logging
import math
import time
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ad_estimator.cli import count, positive, positive_number, seed, write_text_staged
from ad_estimator.metrics import Predictions, compute_metrics, format_table, json_text
from ad_sim import families
from ad_sim.instances import Instance, benchmark
from ad_sim.materials import FAMILIES, FAMILY_RANGES, PARAMETER_NAMES, SAMPLED_PARAMETERS
from ad_sim.mpm import check_device
from ad_sim.resimulate import mask_mse, psnr_from_mse, resimulate
from training.resim_psnr import FIT_VIEW, check_json_out, format_psnr, observed_from_bags, psnr_summary, select

log = logging.getLogger(__name__)

def from_unit(family: str, unit) -> dict[str, float]:
    """A point of [0, 1]^d, where CMA-ES searches -> the family's sampled parameters (SI) over its own sampling
    ranges (log space for E and yield). Coordinates beyond the family's parameters are ignored."""
    return {name: families.from_unit(u, *FAMILY_RANGES[family][name])
            for name, u in zip(SAMPLED_PARAMETERS[family], np.asarray(unit, dtype=np.float64))}


@dataclass
class Fit:
    """Result of one instance's optimisation."""

    episode_id: str
    family: str  # the true family (given)
    parameters: dict[str, float]  # SI, best candidate found
    unit: list[float]  # the same in [0, 1]^d
    loss: float  # mask MSE of the best candidate
    initial_loss: float  # mask MSE at the search's start (the middle of every range)
    history: list[float] = field(default_factory=list)  # best loss after each generation
    evaluations: int = 0  # simulations spent on this instance
    seconds: float = 0.0  # wall time of its batch divided by the instances in the batch

    @property
    def psnr(self) -> float:
        return psnr_from_mse(self.loss)


def search_rng(seed: int, episode_id: str) -> np.random.Generator:
    """The random stream of one instance's CMA-ES. cma samples from numpy's global generator unless
    given its own `randn`, and that would couple the searches of instances optimised together."""
    return np.random.default_rng([seed, zlib.crc32(episode_id.encode())])


def _own_randn(rng: np.random.Generator):
    return lambda rows, columns: rng.standard_normal((rows, columns))


# What CMA-ES is told for a candidate whose loss is not a number (a failed simulation): worse than any mask
# MSE (at most 1 for masks in [0, 1]). cma itself would replace NaN by the generation's median.
FAILED_LOSS = 2.0


def _check_observed(observed: np.ndarray) -> None:
    """Observed videos: uint8 0/255, or float in [0, 1] and finite (a NaN slips past mask_mse's range check
    and would make every loss NaN, found only after the whole search)."""
    observed = np.asarray(observed)
    if observed.ndim != 4 or not min(observed.shape[1:], default=0):
        raise ValueError(f"observed videos must be (N, T, H, W) with T, H, W >= 1, got shape {observed.shape}")
    finite = observed.dtype == np.uint8 or np.all(np.isfinite(observed))
    if not finite or observed.dtype != np.uint8 and not (observed.min() >= 0 and observed.max() <= 1):
        raise ValueError("observed float videos must be finite and in [0, 1] (uint8 masks are read as 0/255)")


def _popsize(text: str) -> int:
    """argparse type of --popsize: CMA-ES needs 2 or more candidates per generation."""
    if not text.isdigit() or int(text) < 2:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 2, got {text!r}")
    return int(text)


def fit_instances(
    instances: list[Instance],
    observed: np.ndarray,
    device: str = "cpu",
    generations: int = 10,
    popsize: int = 16,
    sigma0: float = 0.3,
    seed: int = 0,
    parallel: int = 16,
    progress: bool = True,
) -> list[Fit]:
    """Fits every instance's parameters (its true family) to its observed camera-0 mask video.

    observed: (N, T, H, W) uint8 0/255 (or float in [0, 1]); T frames are simulated per candidate.
    Instances are optimised `parallel` at a time; generation 0 also scores the start point.
    """
    import cma

    if len(observed) != len(instances):
        raise ValueError(f"need one observed video per instance, got {len(observed)} for {len(instances)}")
    if generations < 1 or popsize < 2 or parallel < 1:
        raise ValueError("need generations >= 1, popsize >= 2 and parallel >= 1")
    if len(instances):
        _check_observed(observed)
    frame_count = np.shape(observed)[1]
    chunks = [list(range(i, min(i + parallel, len(instances)))) for i in range(0, len(instances), parallel)]
    bar = tqdm(total=len(chunks) * generations, desc="CMA-ES generations", unit="gen", disable=None if progress else True)
    fits: list[Fit] = []
    for chunk in chunks:
        start = time.perf_counter()
        families = [instances[i].material for i in chunk]
        # Middle of every range. cma fails in 1-D, so sand's friction angle is searched in 2-D with a
        # second coordinate that from_unit ignores (the loss is flat along it).
        starts = [np.full(max(2, len(SAMPLED_PARAMETERS[family])), 0.5) for family in families]
        strategies = [
            cma.CMAEvolutionStrategy(x0, sigma0, {"bounds": [0.0, 1.0], "popsize": popsize, "verbose": -9,
                                                  "randn": _own_randn(search_rng(seed, instances[i].episode_id))})
            for i, x0 in zip(chunk, starts)
        ]
        best = [(math.inf, x0) for x0 in starts]  # (loss, unit point) per instance
        initial = [math.nan] * len(chunk)
        histories: list[list[float]] = [[] for _ in chunk]
        for generation in range(generations):
            asked = [es.ask() for es in strategies]
            # Generation 0 also scores each search's start point.
            points = [([x0] if generation == 0 else []) + list(a) for x0, a in zip(starts, asked)]
            owners = [k for k, p in enumerate(points) for _ in p]
            flat = [u for p in points for u in p]
            candidates = [(families[k], from_unit(families[k], u)) for k, u in zip(owners, flat)]
            masks = resimulate([instances[chunk[k]] for k in owners], candidates, device, FIT_VIEW, frame_count)
            losses = np.asarray(mask_mse(masks, observed[[chunk[k] for k in owners]]), dtype=np.float64)
            offset = 0
            for k, es in enumerate(strategies):
                own = losses[offset : offset + len(points[k])]
                offset += len(points[k])
                if generation == 0:
                    initial[k] = float(own[0])
                # A failed candidate (NaN or infinite loss) is the worst of all: np.argmin would pick a NaN,
                # hiding the generation's best, and cma would take it for the generation's median.
                own = np.where(np.isfinite(own), own, np.inf)
                j = int(np.argmin(own))
                if own[j] < best[k][0]:
                    best[k] = (float(own[j]), np.asarray(points[k][j]))
                es.tell(asked[k], list(np.minimum(own[-len(asked[k]) :], FAILED_LOSS)))
                histories[k].append(best[k][0])
            bar.update()
            bar.set_postfix(mean_best_mse=f"{np.mean([b for b, _ in best]):.2e}")
        seconds = (time.perf_counter() - start) / len(chunk)
        for k, i in enumerate(chunk):
            loss, unit = best[k]
            if not math.isfinite(loss):
                raise ValueError(f"{instances[i].episode_id}: no candidate simulation gave a finite mask loss")
            unit = unit[: len(SAMPLED_PARAMETERS[families[k]])]
            fits.append(Fit(instances[i].episode_id, families[k], from_unit(families[k], unit), unit.tolist(), loss,
                            initial[k], histories[k], generations * popsize + 1, seconds))
    bar.close()
    return fits


def predictions_of(instances: list[Instance], fits: list[Fit]) -> Predictions:
    """The fits as metrics.Predictions: class = true family (probability 1), parameters SI."""
    def row(parameters: dict[str, float]) -> list[float]:
        return [parameters.get(name, math.nan) for name in PARAMETER_NAMES]

    classes = [FAMILIES.index(inst.material) for inst in instances]
    return Predictions(
        true_class=classes,
        true_params=[row({n: inst.parameters[n] for n in SAMPLED_PARAMETERS[inst.material]}) for inst in instances],
        probabilities=np.eye(len(FAMILIES))[classes],
        pred_params=[row(fit.parameters) for fit in fits],
        episode_ids=[inst.episode_id for inst in instances],
    )


def summarise(instances: list[Instance], fits: list[Fit], wall: float) -> dict:
    """Metrics table (metrics.compute_metrics), re-simulation PSNR and time per instance."""
    return {
        "metrics": compute_metrics(predictions_of(instances, fits)),
        "psnr": psnr_summary([inst.material for inst in instances], np.array([fit.psnr for fit in fits])),
        "seconds_per_instance": float(np.mean([fit.seconds for fit in fits])),
        "wall_seconds": wall,
    }


def build_parser(p: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    p = p or argparse.ArgumentParser(prog="python -m training baseline")
    p.description = ("Per-scene optimisation baseline: knowing geometry, initial state, cameras and the true family, "
                     "fit each instance's parameters with CMA-ES over batched re-simulations so that its camera-0 "
                     "masks match the observed ones (loss = mask MSE). Writes a JSON with per-instance fits, the "
                     "metrics table, re-simulation PSNR and seconds per instance. Observed videos are read from "
                     "--bags, or else simulated from the benchmark's ground truth.")
    p.add_argument("--size", default="small", choices=("tiny", "small", "paper"), help="benchmark size (no --bags)")
    p.add_argument("--split", default="unseen", choices=("train", "seen", "unseen"), help="benchmark split (no --bags)")
    p.add_argument("--bags", help="read instances and observed videos from these bags instead of simulating them")
    # Checked here, before the observed videos are simulated (minutes for a paper-size subset), not by
    # fit_instances after them.
    p.add_argument("--instances", type=count, default=16,
                   help="fit a seeded random subset of this many instances (0: all of them)")
    p.add_argument("--generations", type=positive, default=10, help="CMA-ES generations per instance")
    p.add_argument("--popsize", type=_popsize, default=16, help="CMA-ES candidates per generation (>= 2)")
    p.add_argument("--sigma0", type=positive_number, default=0.3,
                   help="initial CMA-ES step size in the normalised [0, 1]^d")
    p.add_argument("--parallel", type=positive, default=16,
                   help="instances optimised together; one simulation batch = parallel x popsize scenes")
    p.add_argument("--device", default="cpu", help="Warp device: cpu, cuda, cuda:N")
    p.add_argument("--seed", type=seed, default=0, help="seeds the subset and every instance's CMA-ES")
    p.add_argument("--out", help="output JSON (default runs/baseline/<size>-<split>.json, or <bags name>.json)")
    p.add_argument("--no-progress", action="store_true")
    return p


def run(args) -> dict:
    check_device(args.device)
    progress = not args.no_progress
    name = Path(args.bags).name if args.bags else f"{args.size}-{args.split}"
    out = Path(args.out or f"runs/baseline/{name}.json")
    check_json_out(out)  # before the simulations and the CMA-ES, not when writing their result
    if args.bags:
        instances, observed = observed_from_bags(args.bags, args.instances, args.seed)
    else:
        every = benchmark(args.size, args.split)
        instances = [every[i] for i in select(args.instances, len(every), args.seed)]
        log.info("simulating the observed videos of %d instances", len(instances))
        observed = resimulate(instances, [(i.material, i.parameters) for i in instances], args.device, FIT_VIEW,
                              progress=progress)
    start = time.perf_counter()
    fits = fit_instances(instances, observed, args.device, args.generations, args.popsize, args.sigma0, args.seed,
                         args.parallel, progress)
    result = summarise(instances, fits, time.perf_counter() - start)
    result["config"] = vars(args)
    result["fits"] = [{**asdict(fit), "psnr": fit.psnr,
                       "true_parameters": {n: inst.parameters[n] for n in SAMPLED_PARAMETERS[inst.material]}}
                      for inst, fit in zip(instances, fits)]
    write_text_staged(out, json_text(result))  # strict JSON: NaN (no instance of a family) becomes null
    print(format_table({str(observed.shape[1]): result["metrics"]}, f"per-scene CMA-ES baseline on {name}"))
    print(format_psnr(result["psnr"], len(fits)))
    print(f"{result['seconds_per_instance']:.2f} s per instance ({len(fits)} instances, {args.generations} x "
          f"{args.popsize} + 1 simulations each, {min(args.parallel, len(fits))} optimised together on {args.device}); "
          f"wrote {out}")
    return result
