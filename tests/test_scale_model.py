"""The scale model (benchmarks/scale/scale_model.py) against cases worked out by hand."""

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks" / "scale"))

import scale_model  # noqa: E402
import scale_validation  # noqa: E402
from scale_model import Costs, Workload, simulate  # noqa: E402

FREE = Costs(driver_iteration_s=0.0, client_task_s=0.0, scheduler_task_s=0.0, worker_task_s=0.0,
             result_delay_s=0.0, hop_s=0.0, step_s=1e-3, client_batch_s=0.0, scheduler_batch_s=0.0)


def test_one_run_on_one_worker_takes_its_work_plus_the_driver_between_iterations():
    workload = Workload(runs=1, iterations=5, batch=8, lengths=[np.array([100, 300])])
    work = workload.episodes().sum() * 1e-3
    free = simulate(workload, 1, FREE)
    assert free["search_s"] == pytest.approx(work) and free["efficiency"] == pytest.approx(1.0)
    costly = simulate(workload, 1, Costs(**{**FREE.__dict__, "driver_iteration_s": 0.05}))
    # the search phase runs from the first batch's sending: four more driver turns in it
    assert costly["search_s"] == pytest.approx(work + 4 * 0.05)


def test_an_iteration_of_two_batches_flies_them_in_turn_each_of_its_own_size():
    """ME-ES's samples, then its offspring: a lone run on 8 workers flies its 8 samples of 100
    steps in the engine's chunks, then its 1 offspring, each batch once the last is told; the
    driver turns once a batch."""
    workload = Workload(runs=1, iterations=6, batch=(8, 1), lengths=[np.array([100])])
    assert [workload.size(k) for k in range(4)] == [8, 1, 8, 1]
    chunks = scale_model.chunk_sizes(8, 8, 1)  # [4, 4]: at least MIN_CHUNK rollouts a chunk
    path = 3 * max(chunks) * 0.1 + 3 * 0.1  # each samples' batch its largest chunk, then one episode
    free = simulate(workload, 8, FREE)
    assert free["search_s"] == pytest.approx(path) and free["ideal_s"] == pytest.approx(path)
    assert free["tasks_per_batch"] == pytest.approx((3 * len(chunks) + 3 * 1) / 6)
    costly = simulate(workload, 8, Costs(**{**FREE.__dict__, "driver_iteration_s": 0.05}))
    assert costly["search_s"] == pytest.approx(path + 5 * 0.05)


def test_a_batch_is_split_as_the_engine_splits_it():
    assert scale_model.chunk_sizes(150, 2, 1) == [38, 38, 37, 37]  # a lone run: 2 chunks per worker
    assert len(scale_model.chunk_sizes(150, 16, 1)) == 32  # whatever its workers
    assert len(scale_model.chunk_sizes(150, 17, 4)) == 13  # 4 runs, 4.25 workers each: ceil(3 x 17 / 4)
    assert len(scale_model.chunk_sizes(150, 16, 8)) == 6  # runs with two workers each: still 3
    assert len(scale_model.chunk_sizes(150, 16, 9)) == 4  # fewer: 2, ceil(2 x 16 / 9)
    assert sum(scale_model.chunk_sizes(150, 512, 1)) == 150
    assert min(scale_model.chunk_sizes(150, 512, 1)) >= 4  # MIN_CHUNK rollouts at least
    assert len(scale_model.chunk_sizes(150, 64, 60)) == 3  # 60 runs share the workers: ceil(2 x 64 / 60)
    assert len(scale_model.chunk_sizes(150, 256, 60)) == 13  # 60 runs, 4.3 workers each: ceil(3 x 256 / 60)


def test_a_busy_driver_is_the_limit_and_parts_lift_it():
    workload = Workload(runs=40, iterations=4, batch=20, lengths=[np.array([50])])
    costs = Costs(**{**FREE.__dict__, "driver_iteration_s": 0.02})
    one, four = simulate(workload, 200, costs), simulate(workload, 200, costs, parts=4, schedulers=4)
    assert one["driver_busy"] > 0.85 and one["efficiency"] < 0.5
    assert four["efficiency"] > 1.8 * one["efficiency"]  # each driver has a quarter of the runs
    assert one["ideal_s"] == pytest.approx(four["ideal_s"])  # the same work, dealt otherwise


def test_processes_sharing_one_core_wait_for_each_other():
    workload = Workload(runs=2, iterations=3, batch=4, lengths=[np.array([10])])
    costs = Costs(**{**FREE.__dict__, "driver_iteration_s": 0.05})
    apart = simulate(workload, 8, costs, parts=2, schedulers=2)
    shared = simulate(workload, 8, Costs(**{**costs.__dict__, "cores": 1}), parts=2, schedulers=2)
    # two drivers on two cores tell and ask at once; on one core, one after the other: the
    # second run's first batch leaves a driver's turn later, and later turns collide again
    assert apart["search_s"] + 0.05 <= shared["search_s"] <= apart["search_s"] + 3 * 0.05 + 1e-9


def test_a_result_lands_at_its_driver_no_sooner_than_its_landing_time():
    workload = Workload(runs=1, iterations=5, batch=8, lengths=[np.array([100, 300])])
    work = workload.episodes().sum() * 1e-3
    landing = simulate(workload, 1, Costs(**{**FREE.__dict__, "landing_s": 0.04}))
    # one worker, one run: each of the four batches after the first waits for its last result
    assert landing["search_s"] == pytest.approx(work + 4 * 0.04)
    assert landing["cycle_back_ms"] == pytest.approx(40.0)
    # a landing shorter than the modelled hops changes nothing
    hops = Costs(**{**FREE.__dict__, "hop_s": 0.01})
    assert simulate(workload, 1, Costs(**{**hops.__dict__, "landing_s": 0.001}))["search_s"] == \
        pytest.approx(simulate(workload, 1, hops)["search_s"])


def test_a_server_is_not_held_for_a_job_still_on_its_way():
    """A result sent to a driver lands later; a tell that is there now goes first. (Booked at
    once, the late job held the driver idle until it landed, and the tell waited behind it.)"""
    sim, ends = scale_model.Simulation(), {}
    driver = scale_model.Server(sim)
    assert driver.serve(1.0, 0.1, lambda t: ends.setdefault("landed", t)) is None  # on its way
    assert driver.serve(0.0, 0.2, lambda t: ends.setdefault("told", t)) == 0.0  # starts at once
    sim.run()
    assert ends == {"told": pytest.approx(0.2), "landed": pytest.approx(1.1)}


def test_a_batched_stream_sends_at_once_or_with_the_next_batch():
    stream = scale_model.Stream(0.010)
    assert stream.depart(1.0) == 1.0  # idle: at once
    assert stream.depart(1.004) == pytest.approx(1.010)  # 10 ms after the last batch
    assert stream.depart(1.006) == pytest.approx(1.010)  # with the batch waiting to leave
    assert stream.depart(1.030) == 1.030  # the interval has passed: at once


def test_batched_streams_idle_between_batches_delay_nothing():
    """One run on one worker: every message finds its stream idle for longer than its interval."""
    workload = Workload(runs=1, iterations=5, batch=8, lengths=[np.array([100, 300])])
    batched = simulate(workload, 1, Costs(**{**FREE.__dict__, "client_batch_s": 0.010,
                                             "scheduler_batch_s": 0.005}))
    assert batched["search_s"] == pytest.approx(workload.episodes().sum() * 1e-3)


def test_saves_take_the_drivers_time_and_drawings_a_workers():
    """One run on one worker, saving after iterations 2 and 4 of 5 (and its last, after the
    search), each save after the next batch is sent: in the driver, a save longer than that
    batch's flight delays the one after; a drawing on the cluster queues behind that batch's
    chunks and delays the next batch (the first drawing with its imports); a saver process
    delays nothing, and is only counted."""
    workload = Workload(runs=1, iterations=5, batch=8, lengths=[np.array([100, 300])])
    flights = workload.episodes().sum(axis=2)[0] * 1e-3
    work = flights.sum()
    saving = {**FREE.__dict__, "log_every": 2}
    short = simulate(workload, 1, Costs(**{**saving, "save_s": flights[2] / 2}))
    assert short["search_s"] == pytest.approx(work)  # hidden behind iteration 3's flight
    long = simulate(workload, 1, Costs(**{**saving, "save_s": 3.0}))
    assert long["search_s"] == pytest.approx(work + 3.0 - flights[2])
    on_worker = simulate(workload, 1, Costs(**{**saving, "draw_s": 0.25, "first_draw_s": 2.0}))
    assert on_worker["search_s"] == pytest.approx(work + 2.0)
    in_process = simulate(workload, 1, Costs(**{**saving, "saver_s": 0.3}))
    assert in_process["search_s"] == pytest.approx(work)
    assert in_process["saver_busy"] == pytest.approx(3 * 0.3 / work)


def test_the_way_back_is_a_landing_then_a_wait_for_the_driver():
    """One run on one worker: every last result lands 40 ms after its chunk and finds the driver
    idle. With a save of 1 s after each sending, longer than a batch's 0.8 s flight, the results
    of every batch after the first find the driver busy and wait for it."""
    workload = Workload(runs=1, iterations=5, batch=8, lengths=[np.array([100])])
    idle = simulate(workload, 1, Costs(**{**FREE.__dict__, "landing_s": 0.04}))
    assert idle["cycle_back_landing_ms"] == pytest.approx(40.0) and idle["cycle_back_waiting_ms"] == 0.0
    assert idle["last_result_lands_driver_idle"] == 1.0
    busy = simulate(workload, 1, Costs(**{**FREE.__dict__, "landing_s": 0.04, "log_every": 1, "save_s": 1.0}))
    assert busy["last_result_lands_driver_idle"] == pytest.approx(1 / 5)
    # the save outlasts the flight and its landing by 0.16 s, for 4 of the 5 batches
    assert busy["cycle_back_waiting_ms"] == pytest.approx(4 / 5 * 1000 * (1.0 - 0.8 - 0.04))


def test_the_drivers_turns_are_drawn_from_their_measured_spread():
    """Turns of 0 or 2x the mean (0.05 s): 199 turns add 0.1 s each time a long one is drawn,
    about half the time."""
    workload = Workload(runs=1, iterations=200, batch=4, lengths=[np.array([10])])
    work = workload.episodes().sum() * 1e-3
    costs = Costs(**{**FREE.__dict__, "driver_iteration_s": 0.05})
    assert simulate(workload, 1, costs)["search_s"] == pytest.approx(work + 199 * 0.05)
    spread = simulate(workload, 1, Costs(**{**costs.__dict__, "driver_spread": (0.0, 2.0)}))
    long_turns = (spread["search_s"] - work) / 0.1
    assert long_turns == pytest.approx(round(long_turns)) and 70 < long_turns < 130


def test_a_part_whose_driver_starts_later_ends_later():
    """Two parts, a run each, each on workers of its own: the second driver starts 0.5 s after
    the first, and the search, from the first batch to the last chunk, lasts 0.5 s longer."""
    workload = Workload(runs=2, iterations=3, batch=4, lengths=[np.array([100])])
    together = simulate(workload, 8, FREE, parts=2, schedulers=2)
    starts = Costs(**{**FREE.__dict__, "part_starts": (0.0, 0.5)})
    later = simulate(workload, 8, starts, parts=2, schedulers=2)
    assert later["search_s"] == pytest.approx(together["search_s"] + 0.5)


def test_the_client_thread_waits_for_the_gil_while_the_main_thread_works():
    """The main thread at work from 0 to 1 s: the client's thread gets the GIL after its wait
    (0.1 s), or when the work ends if that is sooner, and at once while the main thread is idle."""
    for wait, expected in ((0.1, [0.3, 1.0, 1.5]), (0.0, [0.2, 0.95, 1.5])):
        sim = scale_model.Simulation()
        main = scale_model.Server(sim)
        gil = scale_model.GIL(sim, main, wait)
        main.serve(0.0, 1.0, lambda t: None)
        times = []
        for at in (0.2, 0.95, 1.5):
            gil.take(at, times.append)
        sim.run()
        assert times == pytest.approx(expected)


def test_work_booked_back_to_back_keeps_the_gil():
    """A job booked as the last one ends keeps the main thread at work: the client's thread,
    waiting since 0.5 s with a long wait, gets the GIL when the second job ends."""
    sim = scale_model.Simulation()
    main = scale_model.Server(sim)
    gil = scale_model.GIL(sim, main, 10.0)
    main.serve(0.0, 1.0, lambda t: main.serve(t, 1.0, lambda _: None))
    times = []
    gil.take(0.5, times.append)
    sim.run()
    assert times == pytest.approx([2.0])


def test_a_result_that_finds_the_driver_at_work_lands_when_the_gil_is_free():
    """Two runs, two workers, driver turns of 0.5 s, one iteration: run 0's batch leaves when
    the GIL's wait (0.1 s) ends in run 1's turn, flies 0.1 s, and its result lands after another
    wait, at 0.8 s (a landing of 0.1 s), then waits for run 1's turn to end at 1 s. Run 1's
    result comes at 1.1 s, during run 0's last tell, lands at 1.2 s and is taken at 1.5 s."""
    workload = Workload(runs=2, iterations=1, batch=1, lengths=[np.array([100])])
    costs = Costs(**{**FREE.__dict__, "driver_iteration_s": 0.5, "gil_s": 0.1})
    out = simulate(workload, 2, costs)
    assert out["cycle_back_landing_ms"] == pytest.approx(100.0)
    assert out["cycle_back_waiting_ms"] == pytest.approx((200.0 + 300.0) / 2)
    assert out["last_result_lands_driver_idle"] == 0.0
    assert out["result_lands_ms_mean"] == pytest.approx(100.0)


def test_a_schedulers_first_graph_holds_the_first_tasks_back():
    """One run, one worker: its scheduler's first graph (imports) takes 0.3 s, and the run's
    first batch starts that much later."""
    workload = Workload(runs=1, iterations=3, batch=4, lengths=[np.array([100])])
    ready = simulate(workload, 1, FREE)
    held = simulate(workload, 1, Costs(**{**FREE.__dict__, "first_task_waits": (0.3,)}))
    assert held["search_s"] == pytest.approx(ready["search_s"] + 0.3)
    assert held["cycle_to_start_first_ms"] == pytest.approx(300.0)
    assert held["first_task_starts_s"] == pytest.approx([0.3])


def test_a_wall_time_measured_on_the_shared_cores_is_not_slowed_again():
    """One CPU shared by three servers: a job started while two others are busy takes three times
    its CPU, but a wall time (a scheduler's first graph, as measured) takes what it took."""
    sim, machine = scale_model.Simulation(), ([], 1)
    busy, measured, shared = (scale_model.Server(sim, machine) for _ in range(3))
    busy.serve(0.0, 1.0, lambda t: None)
    measured.serve(0.0, 0.3, lambda t: None, wall=True)
    shared.serve(0.0, 0.3, lambda t: None)
    assert measured.free_at == pytest.approx(0.3)
    assert shared.free_at == pytest.approx(0.9)


def test_first_batches_are_sized_for_the_runs_opened_so_far():
    """Four runs on 16 workers, one iteration: the driver sends each run's first batch as it
    opens it, sized for 1, 2, 3 and 4 runs in flight (32, 24, 16 and 12 chunks)."""
    workload = Workload(runs=4, iterations=1, batch=150, lengths=[np.array([10])])
    sizes = [len(scale_model.chunk_sizes(150, 16, n)) for n in (1, 2, 3, 4)]
    assert sizes == [32, 24, 16, 12]
    assert simulate(workload, 16, FREE)["tasks_per_batch"] == pytest.approx(sum(sizes) / 4)
    # two parts: each driver has opened its first run when it sends it
    two = simulate(workload, 16, FREE, parts=2, schedulers=2)
    halves = [len(scale_model.chunk_sizes(150, 8, n)) for n in (1, 1, 2, 2)]
    assert two["tasks_per_batch"] == pytest.approx(sum(halves) / 4)


def test_the_landing_outside_the_gil_is_solved_from_the_measured_one():
    """A measured landing of 60 ms holds the GIL's wait: the fitted model's mean landing is the
    measured one, with less of it outside the GIL."""
    workload = Workload(runs=4, iterations=6, batch=8, lengths=[np.array([20, 60])])
    costs = Costs(**{**FREE.__dict__, "driver_iteration_s": 0.03, "gil_s": 0.02, "landing_s": 0.06})
    fitted, out = scale_validation.fitted_landing(lambda c: simulate(workload, 4, c), costs)
    assert out["result_lands_ms_mean"] == pytest.approx(60.0, abs=1.0)
    assert fitted.landing_s < 0.06


def test_the_benchmark_splits_each_runs_first_batch_apart():
    """bench_scale.py's record of one driver, two runs of two iterations: each run's first batch
    (sent while the driver opens the other) is also split apart, and the driver's wait for its
    first task is from its first batch's sending to the first start of any task."""
    import scale_records

    batches = [{"run": "a", "submitted": 0.0, "keys": ["a0"]}, {"run": "b", "submitted": 0.1, "keys": ["b0"]},
               {"run": "a", "submitted": 2.0, "keys": ["a1"]}, {"run": "b", "submitted": 2.1, "keys": ["b1"]}]
    tells = [{"run": "a", "at": 1.9}, {"run": "b", "at": 2.05},
             {"run": "a", "at": 3.0}, {"run": "b", "at": 3.1}]
    log = {"a0": (0.8, 1.5), "b0": (0.9, 1.6), "a1": (2.1, 2.8), "b1": (2.2, 2.9)}
    landed = {"a0": 1.6, "b0": 1.7, "a1": 2.9, "b1": 3.0}
    split = scale_records.cycles(batches, tells, log, landed)
    assert split["to_start_first"] == pytest.approx([0.8, 0.8])
    assert split["back_landing_first"] == pytest.approx([0.1, 0.1])
    assert split["back_waiting_first"] == pytest.approx([0.3, 0.35])
    assert split["to_start"] == pytest.approx([0.8, 0.8, 0.1, 0.1])
    assert scale_records.first_task_starts([{"batches": batches}], log) == pytest.approx([0.8])


def test_the_benchmark_splits_the_way_to_the_first_start():
    """bench_scale.py's way out of a batch, for its chunk that starts first: to its scheduler (its
    graph taken in), to its handing out there and to its worker process, from the times the
    scheduler's and the workers' logs give by task."""
    import scale_records

    batches = [{"run": "a", "submitted": 0.0, "keys": ["a0", "a0b"]},
               {"run": "a", "submitted": 2.0, "keys": ["a1"]}]
    tells = [{"run": "a", "at": 1.9}, {"run": "a", "at": 3.0}]
    log = {"a0": (0.9, 1.5), "a0b": (0.8, 1.4), "a1": (2.1, 2.8)}  # a0b starts first
    way_out = ({"a0": 0.01, "a0b": 0.02, "a1": 2.03},  # taken in by the scheduler
               {"a0": 0.5, "a0b": 0.6, "a1": 2.05},  # handed out to a worker
               {"a0": 0.55, "a0b": 0.7, "a1": 2.08})  # at the worker
    split = scale_records.cycles(batches, tells, log, {}, way_out)
    assert split["to_scheduler"] == pytest.approx([0.02, 0.03])
    assert split["to_assigned"] == pytest.approx([0.6, 0.05])
    assert split["to_worker"] == pytest.approx([0.7, 0.08])
    assert split["to_worker_first"] == pytest.approx([0.7])
    assert split["to_start"] == pytest.approx([0.8, 0.1])
    assert scale_records.cycles(batches, tells, log, {})["to_scheduler"] == []  # an older record


def test_the_model_splits_the_way_to_the_first_start():
    """One run of two chunks on one worker thread, worked out by hand: 5 ms a hop, and the
    scheduler takes the batch's graph in at 1 ms a task (half its 2 ms) before it hands the first
    chunk out."""
    workload = Workload(runs=1, iterations=1, batch=8, lengths=[np.array([100])])
    costs = Costs(**{**FREE.__dict__, "hop_s": 0.005, "scheduler_task_s": 0.002, "saturation": 1.0,
                     "chunks_per_worker": 2})
    out = simulate(workload, 1, costs)
    assert out["tasks_per_batch"] == 2
    assert out["cycle_to_scheduler_ms"] == pytest.approx(5.0 + 2.0)  # a hop, then 2 x 1 ms
    assert out["cycle_to_assigned_ms"] == pytest.approx(7.0)  # a free slot: handed out at once
    assert out["cycle_to_worker_ms"] == pytest.approx(12.0)  # one hop more
    assert out["cycle_to_start_ms"] == pytest.approx(12.0)
    assert out["first_task_starts_s"] == pytest.approx([0.012])


def test_a_graph_taken_in_as_measured_takes_that_long_whatever_its_tasks():
    """The case above with the graph's intake measured (3 ms, a wall time): the batch reaches the
    scheduler after a hop and the intake, not after half of each task's scheduler CPU (2 x 1 ms);
    its tasks' whole CPU is spent at their ends: the second chunk, handed out when the first's
    end is taken in there, starts 2 ms after it, not 1."""
    workload = Workload(runs=1, iterations=1, batch=8, lengths=[np.array([100])])
    costs = Costs(**{**FREE.__dict__, "hop_s": 0.005, "scheduler_task_s": 0.002, "saturation": 1.0,
                     "chunks_per_worker": 2})
    halves = simulate(workload, 1, costs)
    measured = simulate(workload, 1, dataclasses.replace(costs, intake_s=0.003))
    assert halves["cycle_to_scheduler_ms"] == pytest.approx(5.0 + 2.0)
    assert measured["cycle_to_scheduler_ms"] == pytest.approx(5.0 + 3.0)
    assert measured["cycle_flying_ms"] - halves["cycle_flying_ms"] == pytest.approx(1.0)


def test_the_benchmark_leaves_each_schedulers_first_graph_out_of_the_intake():
    """Two schedulers' graphs: the first of each (its imports) is left out of the mean."""
    import scale_records

    assert scale_records.graph_intake([[0.5, 0.002, 0.004], [0.9, 0.006]]) == {
        "graph_intake_ms_mean": pytest.approx(4.0)}
    assert scale_records.graph_intake([]) == {}


def test_a_worker_slot_is_held_until_its_tasks_end_is_reported():
    """One worker thread with one slot, a batch of two chunks of 0.4 s: the second is handed out
    when the scheduler learns of the first's end, 50 ms after it (`report_s`)."""
    workload = Workload(runs=1, iterations=1, batch=8, lengths=[np.array([100])])
    costs = Costs(**{**FREE.__dict__, "saturation": 1.0, "chunks_per_worker": 2})
    assert simulate(workload, 1, costs)["cycle_flying_ms"] == pytest.approx(800.0)
    reported = simulate(workload, 1, dataclasses.replace(costs, report_s=0.05))
    assert reported["cycle_flying_ms"] == pytest.approx(850.0)


def test_an_idle_driver_takes_a_result_when_it_wakes():
    """One run, one chunk an iteration: each result finds the driver idle, which wakes 20 ms
    later (`wake_s`); the search, from the first batch to the last chunk's end, waits for two."""
    workload = Workload(runs=1, iterations=3, batch=4, lengths=[np.array([100])])
    free = simulate(workload, 1, FREE)
    woken = simulate(workload, 1, dataclasses.replace(FREE, wake_s=0.02))
    assert free["cycle_back_waiting_ms"] == pytest.approx(0.0)
    assert woken["cycle_back_waiting_ms"] == pytest.approx(20.0)
    assert woken["last_result_lands_driver_idle"] == 1.0
    assert woken["search_s"] == pytest.approx(free["search_s"] + 2 * 0.02)


def test_a_task_goes_to_the_least_busy_worker_process_with_a_slot():
    """Two worker processes of two threads, three slots each: a batch of four chunks of 0.4 s is
    dealt two and two, as Dask deals queued tasks (each to the least busy), and flies in one
    chunk's time. (Filled one process after the other, three went to the first, one of them
    waiting there for a thread while a thread of the second stayed idle.)"""
    workload = Workload(runs=1, iterations=1, batch=16, lengths=[np.array([100])])
    costs = Costs(**{**FREE.__dict__, "saturation": 1.5, "chunks_per_worker": 1})
    out = simulate(workload, 4, costs, threads=2)
    assert out["tasks_per_batch"] == 4
    assert out["cycle_flying_ms"] == pytest.approx(400.0)


def test_a_task_reaches_its_worker_no_sooner_than_measured():
    """One thread, two slots, two chunks of 0.4 s: each reaches the worker process 20 ms after its
    handing out (`reach_s`), and the first starts then; the second, there already, waits for the
    thread."""
    workload = Workload(runs=1, iterations=1, batch=8, lengths=[np.array([100])])
    costs = Costs(**{**FREE.__dict__, "saturation": 2.0, "chunks_per_worker": 2, "reach_s": 0.02})
    out = simulate(workload, 1, costs)
    assert out["cycle_to_assigned_ms"] == pytest.approx(0.0)
    assert out["cycle_to_worker_ms"] == pytest.approx(20.0)
    assert out["cycle_to_start_ms"] == pytest.approx(20.0)
    assert out["cycle_flying_ms"] == pytest.approx(800.0)
    # a hop longer than the measured reach is what it takes
    slow = simulate(workload, 1, dataclasses.replace(costs, hop_s=0.03))
    assert slow["cycle_to_worker_ms"] - slow["cycle_to_assigned_ms"] == pytest.approx(30.0)


def test_a_worker_process_starts_a_task_when_its_loop_gets_to_it():
    """One thread, two slots, two chunks of 0.4 s: the first starts 30 ms after it reaches the
    worker process (`start_s`), the second, there already, 30 ms after the first ends."""
    workload = Workload(runs=1, iterations=1, batch=8, lengths=[np.array([100])])
    costs = Costs(**{**FREE.__dict__, "saturation": 2.0, "chunks_per_worker": 2, "start_s": 0.03})
    out = simulate(workload, 1, costs)
    assert out["cycle_to_worker_ms"] == pytest.approx(0.0)
    assert out["cycle_to_start_ms"] == pytest.approx(30.0)
    assert out["cycle_flying_ms"] == pytest.approx(400.0 + 30.0 + 400.0)


def test_the_benchmark_times_each_tasks_way_to_its_worker_and_its_start_there():
    """Three tasks on one thread of a worker process: each reaches the process 10 ms after its
    handing out; the first starts 5 ms after, the second waits for the first's end and starts
    20 ms after it, the third reaches the process after the thread is free and starts 2 ms
    later. A record without the threads gives nothing."""
    import scale_records

    log = {"a": (0.015, 0.5, "1-7"), "b": (0.52, 1.0, "1-7"), "c": (1.502, 2.0, "1-7")}
    assigned = {"a": 0.0, "b": 0.0, "c": 1.49}
    reached = {"a": 0.01, "b": 0.01, "c": 1.5}
    times = scale_records.at_the_workers(log, assigned, reached)
    assert times == {"task_reaches_ms_mean": pytest.approx(10.0), "task_starts_ms_mean": pytest.approx(9.0)}
    assert scale_records.at_the_workers({k: v[:2] for k, v in log.items()}, assigned, reached) == {}


def test_the_benchmark_keeps_each_graphs_intake_on_a_real_scheduler():
    """bench_scale.py's hook on Dask's own timing of update_graph: two graphs sent, two intakes
    kept, each a positive wall time."""
    import bench_scale
    from dask.distributed import Client, LocalCluster

    cluster = LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None)
    with cluster, Client(cluster) as client:
        client.run_on_scheduler(bench_scale.record_graph_intakes)
        assert client.submit(sum, [1, 2]).result() == 3
        assert client.gather(client.map(abs, [-3, -4])) == [3, 4]
        intakes = client.run_on_scheduler(bench_scale.graph_intakes)
    assert len(intakes) == 2 and all(value > 0 for value in intakes)


def test_validation_of_a_file_that_is_not_a_results_file_is_one_line(tmp_path):
    """A missing file, a file that is not JSON and JSON of another benchmark: one line each, no
    traceback; a results file measured without --lengths says so."""
    (tmp_path / "notes.txt").write_text("not json")
    (tmp_path / "other.json").write_text('{"episodes": {"lengths": "x.npz"}}')
    (tmp_path / "short.json").write_text('{"episodes": {}, "rows": []}')
    for name, says in (("missing.json", "FileNotFoundError"), ("notes.txt", "JSONDecodeError"),
                       ("other.json", "KeyError('rows')"), ("short.json", "measured without --lengths")):
        with pytest.raises(SystemExit) as stop:
            scale_validation.validate(str(tmp_path / name))
        assert says in str(stop.value) and "\n" not in str(stop.value)


def test_a_results_file_finds_its_episode_lengths_where_they_moved(tmp_path):
    """A results file names the lengths where they were when it was measured; moved together, they
    are found beside it (or in the scale folder), and the committed results file finds its own."""
    import json

    (tmp_path / "lengths.npz").write_bytes(b"")
    results = str(tmp_path / "results.json")
    moved = {"episodes": {"lengths": "elsewhere/lengths.npz"}}
    assert scale_validation.lengths_file(moved, results) == str(tmp_path / "lengths.npz")
    with pytest.raises(SystemExit, match="are not there"):
        scale_validation.lengths_file({"episodes": {"lengths": "elsewhere/none.npz"}}, results)
    committed = scale_validation.HERE / "scale_results.json"
    found = scale_validation.lengths_file(json.loads(committed.read_text()), str(committed))
    assert Path(found).is_file() and Path(found).name == "episode_lengths_lander.npz"
