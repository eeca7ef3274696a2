"""Rendered cameras: ``characterize``, ``fit-noise``."""

from __future__ import annotations

from pathlib import Path

import typer

from swarm.cli.common import ClusterOpt, ResumeOpt, SetOpt, _load, _progress, _report_failed, _study, app, console


@app.command()
def characterize(
    pipeline: str = typer.Option(..., "--pipeline", help="mono or stereo"),
    out: Path = typer.Option(..., "--out", "-o", help="folder for the JSON table and the Figure 5.7 plots"),
    scenario: Path | None = typer.Option(None, help="take cameras, lighting and noise from this scenario's vision section"),
    sets: list[str] | None = SetOpt,
    ranges: str = typer.Option("3,6,9,12,15,18,21,24,27,30,33", help="comma-separated ranges (m)"),
    orientations: int = typer.Option(6, min=1, help="target attitudes (Fibonacci sphere; the dissertation: 20)"),
    suns: int = typer.Option(6, min=1, help="Sun directions (Fibonacci sphere; the dissertation: 20)"),
    illumination: str = typer.Option("solar,global", help="solar (Sun only) and/or global (Sun + ambient)"),
    seed: int = typer.Option(0, help="seed of the Monte Carlo draws"),
    workers: int = typer.Option(1, "--workers", "-w", min=1, help="parallel worker processes (each renders on its own)"),
    cluster: str | None = ClusterOpt,
    resume: bool = ResumeOpt,
):
    """Monte Carlo error characterisation of a pose pipeline (range × attitude × Sun).

    Writes OUT/characterization-<pipeline>-<W>x<H>-f<focal>.json (usable as
    vision.covariance.table) and OUT/fig5_7_<pipeline>.png, OUT/success_<pipeline>.png.
    The work is cut into cells (one illumination at one range) that run in this process,
    in --workers processes or on a Dask cluster; each cell's samples are appended to
    OUT/results.jsonl as it finishes. A failed cell is listed with its error, the table is
    written without it ("missing_cells"), and the exit status is 1.
    """
    if pipeline not in ("mono", "stereo"):
        console.print("[red]error:[/red] --pipeline must be mono or stereo")
        raise typer.Exit(2)
    from swarm.studies.executor import ResultStore, StudyMapper, open_executor
    from swarmvision.characterize import run_cli

    def log(m):
        console.print(m, highlight=False)

    vision = None
    if scenario is not None:
        from swarmvision.characterize import flown_geometry

        sc = _load(scenario, sets)
        vision = sc.vision
        fg = flown_geometry(sc)
        log(f"{sc.name} flies ranges {fg['range_m'][0]:.1f}–{fg['range_m'][2]:.1f} m (median {fg['range_m'][1]:.1f}), "
            f"Sun angles {fg['sun_deg'][0]:.0f}–{fg['sun_deg'][2]:.0f}°: the design should cover them")
    store = ResultStore(out / "results.jsonl", resume=resume)
    try:
        with _study(open_executor, workers, cluster) as ex, _progress() as prog:
            mapper = StudyMapper(ex, store, log=log)
            task = prog.add_task(f"characterize {pipeline}", total=None)
            run_cli(
                pipeline,
                out,
                vision=vision,
                ranges=[float(x) for x in ranges.split(",") if x.strip()],
                orientations=orientations,
                suns=suns,
                illuminations=[x.strip() for x in illumination.split(",") if x.strip()],
                seed=seed,
                log=log,
                progress=lambda k, K: prog.update(task, completed=k, total=K),
                mapper=mapper,
            )
    finally:
        store.close()
    errors = mapper.result.errors if mapper.result is not None else {}  # (set by the characterisation's one study)
    _report_failed(sorted(errors.items()), "cells", out, "illumination@range index")


@app.command("fit-noise")
def fit_noise(
    table: Path = typer.Argument(..., help="a characterization JSON (or .json.gz) with its samples (swarm characterize "
                                 "--out DIR; shipped: swarmvision/data/*-samples.json.gz)"),
    out: Path = typer.Option(..., "--out", "-o", help="error-model JSON to write (vision.covariance.model)"),
    residuals: list[Path] | None = typer.Option(
        None, "--residuals", help="measurements.npz of runs (swarm sim --measurements): the temporal inflation τ "
        "per axis from their normalised errors' autocorrelation (repeatable)"),
    illumination: str | None = typer.Option(None, help="the samples' illumination to fit (default: the first)"),
    max_lag: int = typer.Option(10, min=1, help="longest lag of the autocorrelation (steps)"),
    window: int | None = typer.Option(
        None, min=2, help="the filter's memory W (steps): τ is the variance factor of a W-step mean "
        "(Bartlett weights) instead of the sum of the positive autocorrelations"),
    flight_scale: bool = typer.Option(
        False, "--flight-scale", help="also re-centre each axis's σ on the runs' errors (median (e/σ)² = χ²₁ median), keeping the "
        "characterisation's dependence on the features"),
):
    """Fit the log-linear measurement-noise model of a pose pipeline from characterisation
    samples (and its temporal inflation from runs' residuals); write it and its plots."""
    from swarmvision.fit_noise import fit_noise as fit

    def log(m):
        console.print(m, highlight=False)

    try:
        _, plots = fit(table, out, residuals or (), illumination, max_lag, window, flight_scale, log=log)
    except (OSError, ValueError, KeyError, EOFError) as e:
        console.print(f"[red]error:[/red] {table}: {e}")
        raise typer.Exit(2) from e
    log(f"wrote {out} and {', '.join(map(str, plots))}")
