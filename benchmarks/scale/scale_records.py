"""What the records of one bench_scale.py experiment say: its figures, as bench_scale.py prints and
writes them (`summarise`), from what its driving processes recorded (each batch's submission and
its tasks, each tell, the main thread's waits for a chunk, each result's landing) and what the
schedulers' and workers' logs give by task (each chunk's start and end on its worker, its way out
and its end's report).

- `cycles`: each run-iteration's cycle split (the driver, to the first chunk's start and its
  parts, flying, back and its parts), each run's first batch also apart;
- `driver_starts`, `first_task_starts`: when each driver sent its first batch, how long it takes
  to open a run, and its wait for its first task (its scheduler's first graph);
- `landings_while_idle`, `driver_wall_per_iteration`, `turn_spread`: the drivers' main threads;
- `at_the_workers`: every task's way to its worker process, and on to its start there;
- `graph_intake`: a batch's graph taken in by its scheduler;
- `summarise`: all of it, with the efficiency, the utilisation and the service times per task.
"""

from __future__ import annotations

import bisect
from typing import Callable

import numpy as np

# to a chunk's start, its first parts: to its scheduler, handed out there, at its worker process
OUT = ("to_scheduler", "to_assigned", "to_worker")


def cycles(batches: list[dict], tells: list[dict], log: dict, landed: dict,
           way_out: tuple[dict, ...] = ({}, {}, {})) -> dict[str, list[float]]:
    """Each run-iteration's cycle, split: the driver (from the previous tell to this batch's
    submission), to the first chunk's start, flying (first start to last end), back (last end to
    the tell); to the start's first parts, for the chunk that starts first, the way to the
    scheduler (to its graph taken in there), to its handing out there and to its worker process
    (where `way_out`, those times by task, has them); and back's two parts: its last result's
    landing (last end to the batch's last result in the driver's process) and its wait there for
    the main thread (to the tell), that wait also for the batches told once a run has ended (its
    last save written meanwhile)."""
    noted = ("to_start", *OUT, "flying", "back_landing", "back_waiting")  # each also for first batches
    split: dict[str, list[float]] = {key: [] for key in (
        "driver", "back", "back_waiting_late", *noted, *(f"{key}_first" for key in noted))}
    told: dict[str, list[float]] = {}
    for tell in tells:
        told.setdefault(tell["run"], []).append(tell["at"])
    first_end = min(times[-1] for times in told.values())
    def note(key: str, value: float, k: int) -> None:  # a run's first batch (k 0): also apart
        split[key].append(value)
        if k == 0:
            split[f"{key}_first"].append(value)

    seen: dict[str, int] = {}
    for batch in batches:
        k = seen[batch["run"]] = seen.get(batch["run"], -1) + 1
        spans = [log[key] for key in batch["keys"] if key in log]
        if not spans or k >= len(told.get(batch["run"], [])):
            continue
        tell_at = told[batch["run"]][k]
        if k > 0:
            split["driver"].append(batch["submitted"] - told[batch["run"]][k - 1])
        starter = min((key for key in batch["keys"] if key in log), key=lambda key: log[key][0])
        first, last = log[starter][0], max(span[1] for span in spans)
        note("to_start", first - batch["submitted"], k)
        for key, times in zip(OUT, way_out):
            if starter in times:
                note(key, times[starter] - batch["submitted"], k)
        note("flying", last - first, k)
        split["back"].append(tell_at - last)
        if (lands := last_landing(batch, landed)) is not None:
            note("back_landing", lands - last, k)
            note("back_waiting", tell_at - lands, k)
            if tell_at > first_end:
                split["back_waiting_late"].append(tell_at - lands)
    return split


def at_the_workers(log: dict, assigned: dict, reached: dict) -> dict[str, float]:
    """Over every task, the means (ms) of its way from its handing out to its worker process, and
    of its wait there from the moment both it and a free thread are there to its start: the
    worker process's event loop, which starts it and hands the thread's last result over (a task
    that waits for a thread waits for the thread's last task's end first). Empty for a record
    without the threads (the log's third field)."""
    keys = [key for key in log if key in assigned and key in reached]
    if not keys or len(log[keys[0]]) < 3:
        return {}
    freed: dict[str, float] = {}  # each thread's last task's end, in start order
    starts = []
    for key in sorted(keys, key=lambda k: log[k][0]):
        start, end, thread = log[key]
        starts.append(start - max(reached[key], freed.get(thread, -np.inf)))
        freed[thread] = end
    return {"task_reaches_ms_mean": round(1000 * float(np.mean([reached[k] - assigned[k] for k in keys])), 1),
            "task_starts_ms_mean": round(1000 * float(np.mean(starts)), 1)}


def graph_intake(intakes: list[list[float]]) -> dict[str, float]:
    """A batch's graph taken in by its scheduler (its update_graph handler, a wall time), the mean
    (ms) over every scheduler's graphs but its first: that one imports the code the tasks name
    (first_task_starts holds it). Empty for a record without them."""
    later = [value for graphs in intakes for value in graphs[1:]]
    return {"graph_intake_ms_mean": round(1000 * float(np.mean(later)), 2)} if later else {}


def last_landing(batch: dict, landed: dict) -> float | None:
    """When the batch's last result landed in its driver's process (None: one never did)."""
    if all(key in landed for key in batch["keys"]):
        return max(landed[key] for key in batch["keys"])
    return None


def turn_spread(turns: list[float]) -> np.ndarray:
    """The spread of the driver's turns (a tell to the next batch's submission): 40 quantiles over
    their mean, the shape the model draws its turns from."""
    return np.quantile(turns, (np.arange(40) + 0.5) / 40) / np.mean(turns)


def driver_starts(records: list[dict]) -> tuple[list[float], float]:
    """When each driving process sent its first batch, from the first of them (the processes
    start one by one), and the time a driver takes to open a run: each driver's span from its
    first batch to its last run's first, over its other runs (mean over the drivers)."""
    firsts = [min(b["submitted"] for b in r["batches"]) for r in records]
    spans = []
    for record, first in zip(records, firsts):
        opened: dict[str, float] = {}
        for batch in record["batches"]:
            opened.setdefault(batch["run"], batch["submitted"])
        spans.append((max(opened.values()) - first) / max(1, len(opened) - 1))
    return [first - min(firsts) for first in firsts], float(np.mean(spans))


def first_task_starts(records: list[dict], log: dict) -> list[float]:
    """Each driving process's wait for its first task to start: from its first batch's
    submission to the first start of any of its tasks. Its scheduler unpickles the first graph
    it is sent (importing the code the tasks name) while the drivers open their runs, so the
    first batches queue there: ~1 s on 2 shared cores, against ~0.05 s later."""
    waits = []
    for record in records:
        starts = [log[key][0] for batch in record["batches"] for key in batch["keys"] if key in log]
        waits.append(min(starts) - record["batches"][0]["submitted"])
    return waits


def landings_while_idle(record: dict, landed: dict) -> tuple[int, int, float]:
    """Of a driving process's batches, how many had their last result land while its main thread
    was waiting for a chunk (idle), how many in all, and the seconds that idle main thread took to
    wake, summed (from the landing to the end of its wait: the GIL and a core). A result reaches
    the driver's process in its client's thread, which needs the GIL the main thread holds while
    it works."""
    waits = sorted(record["waits"])
    starts = [start for start, _ in waits]
    idle = total = 0
    woken = 0.0
    for batch in record["batches"]:
        if (lands := last_landing(batch, landed)) is not None:
            i = bisect.bisect_right(starts, lands) - 1
            if i >= 0 and waits[i][1] >= lands:
                idle, woken = idle + 1, woken + waits[i][1] - lands
            total += 1
    return idle, total, woken


def driver_wall_per_iteration(record: dict, window: tuple[float, float]) -> float:
    """A driving process's main thread: its time at work in `window` (the window less its waits
    for chunks) over the run-iterations it told in it."""
    start, end = window
    waited = sum(max(0.0, min(b, end) - max(a, start)) for a, b in record["waits"])
    told = sum(1 for tell in record["tells"] if start <= tell["at"] < end)
    return (end - start - waited) / max(1, told)


def summarise(workers: int, runs: int, iterations: int, parts: int, records: list[dict], log: dict,
              cpu_between: Callable[[float, float], tuple[float, float]],
              way_out: tuple[dict, ...] = ({}, {}, {}),
              reported: dict | None = None, intakes: list[list[float]] | None = None) -> dict:
    """The figures of one experiment. Its search phase runs from the first batch's submission to
    the last chunk's end: before it, each run's first checkpoint; after it, each run's last save
    (plots, pickles: ~0.5 s a run, which a real 300-iteration run spreads over its iterations).
    Its steady state runs from the moment every run has sent its first batch to the first run's
    last tell: utilisation there is the work the workers did in it over workers x its length."""
    batches = sorted((b for r in records for b in r["batches"]), key=lambda b: b["submitted"])
    tells = [t for r in records for t in r["tells"]]
    tasks = sum(len(b["keys"]) for b in batches)
    latencies = [min(log[k][0] for k in b["keys"] if k in log) - b["submitted"]
                 for b in batches if any(k in log for k in b["keys"])]
    search_s = max(times[1] for times in log.values()) - batches[0]["submitted"]
    scheduler_cpu, worker_cpu = cpu_between(batches[0]["submitted"], batches[0]["submitted"] + search_s)
    work = sum(sum(b["durations"]) for b in batches)
    # no run can be faster than its iterations' longest chunks, one after another
    paths: dict[str, float] = {}
    for batch in batches:
        paths[batch["run"]] = paths.get(batch["run"], 0.0) + max(batch["durations"])
    ideal = max(work / workers, max(paths.values()))
    opened = {}
    for batch in batches:
        opened.setdefault(batch["run"], batch["submitted"])
    last_tells: dict[str, float] = {}
    for tell in tells:
        last_tells[tell["run"]] = max(last_tells.get(tell["run"], 0.0), tell["at"])
    steady = (max(opened.values()), min(last_tells.values()))
    in_window = sum(max(0.0, min(b, steady[1]) - max(a, steady[0])) for a, b, *_ in log.values())
    driver_cpu = [(r["batches"][-1]["cpu"] - r["batches"][0]["cpu"]) / max(1, len(r["batches"]) - 1)
                  for r in records]
    # the main thread's wall time at work (not waiting for a chunk) per run-iteration told in the
    # steady state: on a shared machine it exceeds the CPU the process is given (before it, the
    # runs open; after it, the runs' last saves take the driver's GIL)
    driver_wall = [driver_wall_per_iteration(r, steady) for r in records]
    # from a chunk's end on its worker to its result in the driver's process (as_completed's queue)
    landed = {key: at for r in records for key, at in r["landed"].items()}
    split = cycles(batches, tells, log, landed, way_out)
    starts, opening = driver_starts(records)
    idle, counted, woken = np.sum([landings_while_idle(r, landed) for r in records], axis=0)
    landing = [at - log[key][1] for key, at in landed.items() if key in log]
    # from a chunk's end to its scheduler's knowing it (its worker process's slot free again)
    report = [at - log[key][1] for key, at in (reported or {}).items() if key in log]
    return {"workers": workers, "runs": runs, "iterations": iterations, "parts": parts, "tasks": tasks,
            "tasks_per_batch": round(tasks / len(batches), 2), "work_s": round(work, 2),
            "ideal_s": round(ideal, 3), "search_s": round(search_s, 3),
            "efficiency": round(ideal / search_s, 3),
            "utilisation": round(work / (workers * search_s), 3),
            "steady_utilisation": round(in_window / (workers * (steady[1] - steady[0])), 3)
            if steady[1] > steady[0] else None,
            "last_run_opens_s": round(steady[0] - batches[0]["submitted"], 3),
            "driver_starts_s": [round(start, 3) for start in starts],
            "first_task_starts_s": [round(wait, 3) for wait in first_task_starts(records, log)],
            "run_opens_ms": round(1000 * opening, 2),
            "driver_cpu_ms_per_iteration": round(1000 * float(np.mean(driver_cpu)), 3),
            "driver_wall_ms_per_iteration": round(1000 * float(np.mean(driver_wall)), 3),
            "scheduler_cpu_ms_per_task": round(1000 * scheduler_cpu / tasks, 3),
            "worker_cpu_ms_per_task": round(1000 * worker_cpu / tasks, 3),
            **{f"cycle_{key}_ms": round(1000 * float(np.mean(values)), 1) if values else None
               for key, values in split.items()},
            "late_batches": len(split["back_waiting_late"]),
            "driver_turn_spread": [round(float(q), 3) for q in turn_spread(split["driver"])],
            "result_lands_ms_mean": round(1000 * float(np.mean(landing)), 1),
            **({"result_reported_ms_mean": round(1000 * float(np.mean(report)), 1)} if report else {}),
            **at_the_workers(log, way_out[1], way_out[2]),
            **graph_intake(intakes or []),
            "last_result_lands_driver_idle": round(float(idle / max(1, counted)), 3),
            "driver_wakes_ms_mean": round(1000 * float(woken / max(1, idle)), 1),
            "result_lands_ms_median": round(1000 * float(np.median(landing)), 1),
            "first_start_ms_median": round(1000 * float(np.median(latencies)), 1),
            "first_start_ms_p90": round(1000 * float(np.percentile(latencies, 90)), 1),
            # to the end of the drivers' last save: what a user waits for, last saves included
            "all_saved_s": round(max(r["ended"] for r in records) - batches[0]["submitted"], 3)}
