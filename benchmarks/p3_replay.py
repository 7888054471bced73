# benchmarks/p3_replay.py: P3, observer-eval on a synthetic Imu bag against two baselines.
"""
P3: ``observer-eval`` on a synthetic bag of 10^6 Imu messages (10^4 with ``--smoke``).

The bag is a seeded open-loop simulation of ``config/submarine.yaml``
(``core.simulate.PlantSimulator``: exact ZOH, the gyro's noise) at the vehicle's rate:
``/imu/data`` (sensor_msgs/Imu, one per step), and every 10th step ``/state/true`` and a
new piecewise-constant command on ``/control/u`` (JointState), written with rosbags'
Writer (mcap, version 9). It is generated once into ``~/.cache/observer_ros/benchmarks``
(``$OBSERVER_ROS_BENCH_DATA``) and reused.

Three programs run in fresh processes, alternated over ``--rounds`` rounds (the order
rotates each round); each reports its work time and its peak RSS (``VmHWM`` of /proc/self/status).
The baselines are timed strictly: only their loop or call, imports and set-up
excluded; observer-eval is timed from before its import to its exit status, so it
pays for importing numpy, scipy, python-control and rosbags (about 1 s here):

- ``eval``: ``observer-eval BAG --vehicle config/submarine.yaml --out DIR --no-plots``
  (reading, replay of the design, scoring, table and the results files and bag);
- baseline (a): rosbags ``Reader`` reading every message of the bag and deserialising
  it with ``typestore.deserialize_cdr``;
- baseline (b): python-control ``forced_response`` of the same discrete observer (the
  vehicle's design at the bag's step, current form: inputs [y, u], outputs x_hat) on
  the measurement and command arrays, already in memory.

Figures: eval / (a) and eval / (b), per round [median <= 1.0 each]; peak RSS of eval
per message; the replay's CPU per message of a Kalman variant over the design's
(pole placement), alternated in one process on the recording read once
[median <= 2.0]. ``--big`` also writes a 10^7-message bag (about 3.8 GB, half an hour)
and checks that observer-eval's peak RSS on it is within 1.1x of the rounds' (10^6)
and below 400 MiB, with the time and peak RSS of baseline (a) on the same bag.
``--jitter`` also evaluates the same simulation with every stamp moved by up to +-0.3 ms
(seeded), once per round, against the regular bag's eval of that round [median <= 1.5].
Neither runs by default (minutes to hours); run them on demand.

``--baseline-pythonpath DIR`` (a checkout of an earlier version, e.g. ``git archive``)
also runs that version's observer-eval in each round, right after this version's, on
the same bag (and with ``--big`` on the 10^7 bag): eval / eval of the baseline, per
round [median <= 1.0: no slower per message than that version], and its peak RSS.
The workers find observer-eval's ``main`` and the replay in this tree's layout or in
40ee30d's (``bag/evaluate.py``, ``bag/replay.py``), the commit the figures compare with.

"""

import importlib
import json
import math
import os
from pathlib import Path
import shutil
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import common_parser, log, ratio_line, REPO, report, summary  # noqa: E402

VEHICLE = REPO / 'config' / 'submarine.yaml'
# generated data lives outside the repository (a 10^6-message bag is ~400 MB)
DATA = Path(os.environ.get('OBSERVER_ROS_BENCH_DATA') or
            Path.home() / '.cache' / 'observer_ros' / 'benchmarks')
CMD_EVERY = 10           # steps between commands (and true states)
JITTER_NS = 300_000      # --jitter: every stamp moved by up to +-0.3 ms
FORMAT = 2               # bump when the bag's content changes
GEN_BLOCK = 65_540       # steps simulated and written at a time (a multiple of CMD_EVERY)
WRITE_BLOCK = 4_100      # steps of a block serialised at a time (a multiple of CMD_EVERY)


# ---------------------------------------------------------------- the synthetic bag

def _template(store, msgtype, msg, markers):
    """Serialise msg; return its bytes and the offsets of the marker values (float64)."""
    import numpy as np
    raw = bytes(store.serialize_cdr(msg, msgtype))
    offsets = {}
    for name, value in markers.items():
        pos = raw.find(np.float64(value).tobytes())
        assert pos > 0 and raw.find(np.float64(value).tobytes(), pos + 1) < 0, name
        offsets[name] = pos
    return raw, offsets


def _stamp_offsets(store, make):
    """Offsets of header.stamp.sec and .nanosec: serialise two stamps and compare."""
    a = bytes(store.serialize_cdr(*make(0x01020304, 0x05060708)))
    sec = a.find((0x01020304).to_bytes(4, 'little'))
    nsec = a.find((0x05060708).to_bytes(4, 'little'))
    assert sec > 0 and nsec > 0
    return sec, nsec


def _fill(template, count, stamp_ns, sec_off, nsec_off, doubles):
    """``count`` copies of a template with stamps and float64 fields written in bulk."""
    import numpy as np
    rows = np.frombuffer(template, dtype=np.uint8)[None, :].repeat(count, axis=0)
    sec = (stamp_ns // 1_000_000_000).astype('<i4')
    nsec = (stamp_ns % 1_000_000_000).astype('<u4')
    rows[:, sec_off:sec_off + 4] = sec.view(np.uint8).reshape(count, 4)
    rows[:, nsec_off:nsec_off + 4] = nsec.view(np.uint8).reshape(count, 4)
    for off, values in doubles:
        rows[:, off:off + 8] = np.ascontiguousarray(values, dtype='<f8').view(
            np.uint8).reshape(count, 8)
    return rows


def _npy(path, dtype, shape):
    """Open a .npy file for rows appended a block at a time (the header first)."""
    import numpy as np
    f = open(path, 'wb')
    np.lib.format.write_array_header_1_0(f, {'descr': np.lib.format.dtype_to_descr(
        np.dtype(dtype)), 'fortran_order': False, 'shape': tuple(shape)})
    return f


def generate(messages, seed=0, data=DATA, log=print, jitter_ns=0):
    """
    Write (or reuse) the synthetic bag of ``messages`` Imu messages.

    With ``jitter_ns`` every stamp (and receive time) is moved by a seeded uniform amount
    in [-jitter_ns, jitter_ns] (the order of the messages is kept).

    The simulation, the messages and the arrays go a block of :data:`GEN_BLOCK` steps at
    a time: memory does not grow with ``messages`` (the simulator's random stream is
    drawn step by step as before, so the regular bag is the same one).

    Returns the bag directory; next to it ``arrays/`` holds, for baseline (b), the
    stamps, the measurements and the command held at each measurement (.npy files).

    """
    import numpy as np
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import get_typestore, Stores

    from observer_ros.core.simulate import PlantSimulator
    from observer_ros.vehicle import load_vehicle

    root = Path(data) / (f'imu_{messages}_s{seed}_v{FORMAT}' +
                         (f'_j{jitter_ns}b' if jitter_ns else ''))
    bag = root / 'bag'
    if (root / 'DONE').exists():
        return bag
    if root.exists():
        shutil.rmtree(root)
    (root / 'arrays').mkdir(parents=True)
    t_start = time.perf_counter()
    vehicle = load_vehicle(VEHICLE)
    plant = vehicle.plant
    gyro = vehicle.sensors[0]
    dt = vehicle.sample_time
    rng = np.random.default_rng(seed + 1)
    sim = PlantSimulator(plant, x0=vehicle.simulator.initial_state, seed=seed,
                         measurement_noise_std=np.asarray(gyro.noise_std))
    row = plant.output_rows(gyro.outputs)
    n_cmd = (messages + CMD_EVERY - 1) // CMD_EVERY
    commands = rng.uniform(-0.05, 0.05, size=(n_cmd, plant.m))
    t0_ns = 1_000_000_000
    step_ns = int(round(dt * 1e9))
    np.save(root / 'arrays' / 'dt.npy', np.array(dt))

    store = get_typestore(Stores.ROS2_JAZZY)
    T = store.types
    IMU, JS = 'sensor_msgs/msg/Imu', 'sensor_msgs/msg/JointState'
    field = gyro.fields[0].split('.')        # angular_velocity.y

    def imu(sec=0, nsec=0, value=0.0):
        v = T['geometry_msgs/msg/Vector3']
        cov = np.zeros(9)
        cov[0] = -1.0
        msg = T[IMU](header=T['std_msgs/msg/Header'](
            stamp=T['builtin_interfaces/msg/Time'](sec=sec, nanosec=nsec),
            frame_id=gyro.frame_id),
            orientation=T['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=cov.copy(),
            angular_velocity=v(x=0.0, y=0.0, z=0.0),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=v(x=0.0, y=0.0, z=0.0),
            linear_acceleration_covariance=cov.copy())
        std = float(gyro.noise_std[0])
        axis = 'xyz'.index(field[1])
        msg.angular_velocity_covariance[4 * axis] = std * std
        setattr(getattr(msg, field[0]), field[1], value)
        return msg, IMU

    def vector(names, values, sec=0, nsec=0):
        msg = T[JS](header=T['std_msgs/msg/Header'](
            stamp=T['builtin_interfaces/msg/Time'](sec=sec, nanosec=nsec), frame_id=''),
            name=list(names), position=np.asarray(values, dtype=float),
            velocity=np.zeros(0), effort=np.zeros(0))
        return msg, JS

    marker = 1.2345678901234567e-7
    imu_raw, imu_off = _template(store, IMU, imu(value=marker)[0], {'y': marker})
    imu_sec, imu_nsec = _stamp_offsets(store, lambda s, ns: imu(s, ns, 0.0))
    n, m = plant.n, plant.m
    st_markers = [marker * (i + 2) for i in range(n)]
    st_raw, st_off = _template(store, JS, vector(plant.state_names, st_markers)[0],
                               dict(enumerate(st_markers)))
    st_sec, st_nsec = _stamp_offsets(store, lambda s, ns: vector(plant.state_names,
                                                                 np.zeros(n), s, ns))
    u_markers = [marker * (i + 20) for i in range(m)]
    u_raw, u_off = _template(store, JS, vector(plant.input_names, u_markers)[0],
                             dict(enumerate(u_markers)))
    u_sec, u_nsec = _stamp_offsets(store, lambda s, ns: vector(plant.input_names,
                                                               np.zeros(m), s, ns))
    files = {name: _npy(root / 'arrays' / f'{name}.npy', dtype, shape) for name, dtype, shape
             in (('stamp_ns', np.int64, (messages,)), ('y', np.float64, (messages,)),
                 ('u_held', np.float64, (messages, m)))}
    u = np.zeros(m)
    ns = ''                                  # topics as recorded without a namespace
    checked = False
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        c_imu = writer.add_connection(f'{ns}/{gyro.topic}', IMU, typestore=store)
        c_true = writer.add_connection(f'{ns}/state/true', JS, typestore=store)
        c_u = writer.add_connection(f'{ns}/control/u', JS, typestore=store)
        write = writer.write
        for k0 in range(0, messages, GEN_BLOCK):      # a multiple of CMD_EVERY
            count = min(GEN_BLOCK, messages - k0)
            y = np.empty(count)
            u_held = np.empty((count, m))   # the command held when y_k was measured
            x_true = np.empty(((count + CMD_EVERY - 1) // CMD_EVERY, n))
            for i in range(count):
                k = k0 + i
                if k % CMD_EVERY == 0:
                    x_true[i // CMD_EVERY] = sim.x
                y[i] = sim.measure(row)[0]
                u_held[i] = u
                if k % CMD_EVERY == 0:
                    u = commands[k // CMD_EVERY]
                sim.step(u, dt)
            stamps = t0_ns + step_ns * np.arange(k0, k0 + count, dtype=np.int64)
            if jitter_ns:                   # a seeded stream per block
                stamps += np.random.default_rng([seed + 2, k0 // GEN_BLOCK]).integers(
                    -jitter_ns, jitter_ns + 1, size=count)
            for name, values in (('stamp_ns', stamps), ('y', y), ('u_held', u_held)):
                files[name].write(np.ascontiguousarray(values).tobytes())
            cmds = commands[k0 // CMD_EVERY:k0 // CMD_EVERY + x_true.shape[0]]
            # the messages' bytes a few thousand at a time (a multiple of CMD_EVERY): the
            # templated rows of a whole block would be 25 MB
            for s0 in range(0, count, WRITE_BLOCK):
                s1 = min(count, s0 + WRITE_BLOCK)
                st = stamps[s0:s1]
                imu_rows = _fill(imu_raw, s1 - s0, st, imu_sec, imu_nsec,
                                 [(imu_off['y'], y[s0:s1])])
                c0, c1 = s0 // CMD_EVERY, -(-s1 // CMD_EVERY)
                cmd_stamps = st[::CMD_EVERY]
                st_rows = _fill(st_raw, c1 - c0, cmd_stamps, st_sec, st_nsec,
                                [(st_off[i], x_true[c0:c1, i]) for i in range(n)])
                u_rows = _fill(u_raw, c1 - c0, cmd_stamps, u_sec, u_nsec,
                               [(u_off[i], cmds[c0:c1, i]) for i in range(m)])
                if not checked:     # sanity: the templated bytes deserialise to the values
                    half = (s1 - s0) // 2
                    check = store.deserialize_cdr(imu_rows[half].tobytes(), IMU)
                    assert getattr(getattr(check, field[0]), field[1]) == y[s0 + half]
                    assert check.header.stamp.sec * 10**9 + check.header.stamp.nanosec == \
                        st[half]
                    checked = True
                stamp_list = st.tolist()
                for i in range(s1 - s0):
                    ts = stamp_list[i]
                    if i % CMD_EVERY == 0:
                        write(c_true, ts, st_rows[i // CMD_EVERY].tobytes())
                    write(c_imu, ts, imu_rows[i].tobytes())
                    if i % CMD_EVERY == 0:
                        write(c_u, ts, u_rows[i // CMD_EVERY].tobytes())
            if k0 and k0 % (16 * GEN_BLOCK) == 0:
                log(f'  P3: {k0} of {messages} steps written')
    for f in files.values():
        f.close()
    (root / 'DONE').write_text(json.dumps({'messages': messages, 'seed': seed}))
    log(f'  P3: wrote {bag} ({_size(bag) / 2**20:.0f} MiB) in '
        f'{time.perf_counter() - t_start:.1f} s')
    return bag


def _size(path):
    return sum(p.stat().st_size for p in Path(path).rglob('*') if p.is_file())


# ---------------------------------------------------------------- the three programs

def _maxrss_mib():
    """Peak RSS of this process (VmHWM; getrusage's ru_maxrss survives exec on Linux)."""
    try:
        for line in Path('/proc/self/status').read_text().splitlines():
            if line.startswith('VmHWM:'):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    import resource
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def worker_a(bag):
    """Baseline (a): rosbags reads and deserialises every message."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import get_typestore, Stores
    store = get_typestore(Stores.ROS2_JAZZY)
    t0 = time.perf_counter()
    count = 0
    with Reader(bag) as reader:
        deserialize = store.deserialize_cdr
        for conn, _, raw in reader.messages():
            deserialize(raw, conn.msgtype)
            count += 1
    return {'seconds': time.perf_counter() - t0, 'messages': count}


def worker_b(arrays):
    """Baseline (b): python-control forced_response of the discrete observer, in memory."""
    import numpy as np
    arrays = Path(arrays)
    if arrays.is_dir():
        y, u_held = np.load(arrays / 'y.npy'), np.load(arrays / 'u_held.npy')
        dt = float(np.load(arrays / 'dt.npy'))
    else:                   # a bag generated before the arrays were streamed
        data = np.load(arrays)
        y, u_held, dt = data['y'], data['u_held'], float(data['dt'])
    N = y.size
    import control
    from observer_ros.core.estimators import make_estimator
    from observer_ros.core.model import zoh_matrices
    from observer_ros.vehicle import load_vehicle
    vehicle = load_vehicle(VEHICLE)
    plant = vehicle.plant
    est = make_estimator(plant, vehicle.observer)
    M = est.correction_gain(dt)
    Ad, Bd = zoh_matrices(plant.A, plant.B, dt)
    C, D = plant.C, plant.D
    n = plant.n
    # current form, state s_k = x-_k (prior), inputs [y_k; u_k] (test_core_estimators)
    IMC = np.eye(n) - M @ C
    sys_ = control.ss(Ad @ IMC, np.hstack([Ad @ M, Bd - Ad @ M @ D]), IMC,
                      np.hstack([M, -M @ D]), dt)
    # the input held over step k is the one held when y_{k+1} is measured
    u_step = np.vstack([u_held[1:], u_held[-1:]])
    U = np.vstack([y[None, :], u_step.T])
    t_arr = np.arange(N) * dt
    t0 = time.perf_counter()
    resp = control.forced_response(sys_, T=t_arr, U=U, X0=np.zeros(n))
    x_hat = resp.outputs
    return {'seconds': time.perf_counter() - t0, 'messages': int(N),
            'x_hat_last': np.asarray(x_hat)[:, -1].tolist()}


# where this tree's layout and 40ee30d's differ: the module of each name, this tree's first
LAYOUTS = {'replay': ('observer_ros.replay.replay', 'observer_ros.bag.replay'),
           'main': ('observer_ros.evaluation.evaluate', 'observer_ros.bag.evaluate')}


def _from_layout(name):
    """Return ``name`` from the first of its modules (:data:`LAYOUTS`) that exists."""
    for module in LAYOUTS[name]:
        try:
            return getattr(importlib.import_module(module), name)
        except ModuleNotFoundError as err:      # the module or a package above it
            if not (module + '.').startswith(f'{err.name}.'):
                raise
    raise ModuleNotFoundError(f'none of {", ".join(LAYOUTS[name])}')


KALMAN = ['observer.type:=kalman',
          'observer.Qd:=[1.0e-6,0.0,0.0, 0.0,1.0e-4,0.0, 0.0,0.0,1.0e-4]']


def worker_replay(bag, rounds):
    """Time the replay alone: the design (poles) and a Kalman variant, alternated (us/msg)."""
    import numpy as np  # noqa: F401
    from observer_ros.bag.reader import read_recording
    from observer_ros.vehicle import load_vehicle
    replay = _from_layout('replay')
    design = load_vehicle(VEHICLE)
    kalman = load_vehicle(VEHICLE, overrides=KALMAN)
    recording = read_recording(bag, design)
    out = {'poles': [], 'kalman': [], 'bulk': {}}
    for vehicle in (design, kalman):        # warm: designs, caches, first-use imports
        replay(recording, vehicle, spill=True)
    for _ in range(int(rounds)):
        for name, vehicle in (('poles', design), ('kalman', kalman)):
            t0 = time.process_time()
            rep = replay(recording, vehicle, spill=True)
            seconds = time.process_time() - t0
            out[name].append(seconds / len(rep) * 1e6)
            out['bulk'][name] = [rep.bulk_steps, len(rep), list(rep.warnings)]
            del rep
    return out


def worker_eval(bag, out):
    """observer-eval BAG --vehicle config/submarine.yaml --out OUT --no-plots."""
    t0 = time.perf_counter()
    main = _from_layout('main')
    import contextlib
    import io
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main([str(bag), '--vehicle', str(VEHICLE), '--out', str(out), '--no-plots',
                     '--force'])
    seconds = time.perf_counter() - t0
    if code != 0:
        raise SystemExit(f'observer-eval exited {code}: {buf.getvalue()[-2000:]}')
    return {'seconds': seconds, 'table': buf.getvalue()[-1500:]}


def _run_worker(kind, *args, timeout=3600, pythonpath=None):
    cmd = [sys.executable, '-W', 'ignore', str(Path(__file__).resolve()), '--worker', kind,
           *map(str, args)]
    env = dict(os.environ)
    if pythonpath:      # another version of observer_ros first on the path
        env['PYTHONPATH'] = os.pathsep.join([str(pythonpath), env.get('PYTHONPATH', '')])
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env,
                          cwd=pythonpath or None)
    if proc.returncode != 0:
        raise RuntimeError(f'P3 worker {kind} failed ({proc.returncode}):\n'
                           f'{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}')
    return json.loads(proc.stdout.strip().splitlines()[-1])


# ---------------------------------------------------------------- the benchmark

def run(smoke=False, rounds=None, big=False, messages=None, log=print, jitter=False,
        baseline=None):
    messages = messages or (10_000 if smoke else 1_000_000)
    rounds = rounds or (1 if smoke else 3)
    bag = generate(messages, log=log)
    arrays = bag.parent / 'arrays'
    if not arrays.is_dir():
        arrays = bag.parent / 'arrays.npz'
    results = {'eval': [], 'a': [], 'b': [], 'baseline': []}
    order = ['eval', 'a', 'b']
    with tempfile.TemporaryDirectory(prefix='p3_eval_') as tmp:
        for r in range(rounds):
            for kind in order[r % 3:] + order[:r % 3]:
                if kind == 'eval':
                    res = _run_worker('eval', bag, Path(tmp) / f'out{r}')
                elif kind == 'a':
                    res = _run_worker('a', bag)
                else:
                    res = _run_worker('b', arrays)
                results[kind].append(res)
                log(f'  P3 round {r + 1}/{rounds} {kind:>4}: {res["seconds"]:.2f} s, '
                    f'peak RSS {res["maxrss_mib"]:.0f} MiB')
                if kind == 'eval' and baseline:
                    res = _run_worker('eval', bag, Path(tmp) / f'base{r}',
                                      pythonpath=baseline)
                    results['baseline'].append(res)
                    log(f'  P3 round {r + 1}/{rounds} eval of {baseline}: '
                        f'{res["seconds"]:.2f} s, peak RSS {res["maxrss_mib"]:.0f} MiB')
    figures = []
    if baseline:
        _versus_baseline(figures, results['eval'], results['baseline'], messages, baseline,
                         smoke)
    ev = [x['seconds'] for x in results['eval']]
    for base, label in (('a', 'rosbags_read_deserialise'), ('b', 'control_forced_response')):
        ratios = [e / x['seconds'] for e, x in zip(ev, results[base])]
        figures.append(ratio_line(
            'P3', f'eval/{label}', ratios, '<=', 1.0, smoke=smoke,
            note=f'{messages} Imu msgs; eval median {summary(ev)["median"]:.2f} s, '
                 f'({base}) {summary([x["seconds"] for x in results[base]])["median"]:.2f} s'))
    rss = [x['maxrss_mib'] for x in results['eval']]
    rss_a = [x['maxrss_mib'] for x in results['a']]
    figures.append(ratio_line(
        'P3', 'eval_peak_rss/rosbags_read_peak_rss',
        [e / a for e, a in zip(rss, rss_a)], '<=', None, smoke=smoke,
        note=f'eval {summary(rss)["median"]:.0f} MiB, (a) {summary(rss_a)["median"]:.0f} MiB '
             f'for {messages} msgs (bag {_size(bag) / 2**20:.0f} MiB)'))
    data = {'benchmark': 'P3', 'smoke': smoke, 'messages': messages, 'figures': figures,
            'runs': results, 'bag_mib': _size(bag) / 2**20}
    data['kalman'] = _kalman(bag, messages, rounds, smoke, figures, log, baseline)
    if jitter:
        data['jitter'] = _jitter(messages, rounds, smoke, results['eval'], figures, log)
    if big:
        data['big'] = _big(figures, log, baseline, rss, messages)
    return data


def _versus_baseline(figures, runs, base_runs, messages, baseline, smoke=False):
    """Add the figure: this eval / the baseline version's eval, per round; peak RSS."""
    ev = [x['seconds'] for x in runs]
    bs = [x['seconds'] for x in base_runs]
    figures.append(ratio_line(
        'P3', f'eval/eval_of_baseline[{messages}]', [e / b for e, b in zip(ev, bs)], '<=',
        1.0, smoke=smoke,
        note=f'{messages} Imu msgs; eval median {summary(ev)["median"]:.2f} s '
             f'({summary(ev)["median"] / messages * 1e6:.2f} us per msg), {baseline} '
             f'{summary(bs)["median"]:.2f} s; peak RSS '
             f'{summary([x["maxrss_mib"] for x in runs])["median"]:.0f} against '
             f'{summary([x["maxrss_mib"] for x in base_runs])["median"]:.0f} MiB'))


def _kalman(bag, messages, rounds, smoke, figures, log, baseline=None):
    """Add the figure of the replay's CPU per message: Kalman against the design's poles."""
    res = _run_worker('replay', bag, max(2, rounds))
    ratios = [k / p for k, p in zip(res['kalman'], res['poles'])]
    log(f'  P3 replay per message: poles {res["poles"]}, kalman {res["kalman"]} us '
        f'(bulk steps {res["bulk"]})')
    figures.append(ratio_line(
        'P3', f'kalman_replay/poles_replay_per_msg[{messages}]', ratios, '<=', 2.0,
        smoke=smoke, note=f'CPU per message: kalman {summary(res["kalman"])["median"]:.2f} '
                          f'us, poles {summary(res["poles"])["median"]:.2f} us'))
    out = {'this': res}
    if baseline:
        base = _run_worker('replay', bag, 1, pythonpath=baseline)
        log(f'  P3 replay per message of {baseline}: poles {base["poles"]}, kalman '
            f'{base["kalman"]} us')
        figures.append(ratio_line(
            'P3', f'kalman_replay/kalman_replay_of_baseline[{messages}]',
            [summary(res['kalman'])['median'] / base['kalman'][0]], '<=', 1.0, smoke=smoke,
            note=f'{baseline}: kalman {base["kalman"][0]:.2f} us per message'))
        out['baseline'] = base
    return out


def _jitter(messages, rounds, smoke, regular, figures, log):
    """Eval of the same bag with stamps jittered by +-JITTER_NS, against the regular one."""
    bag = generate(messages, jitter_ns=JITTER_NS, log=log)
    runs = []
    with tempfile.TemporaryDirectory(prefix='p3_jitter_') as tmp:
        for r in range(min(rounds, len(regular))):
            res = _run_worker('eval', bag, Path(tmp) / f'out{r}')
            runs.append(res)
            log(f'  P3 jitter round {r + 1}: {res["seconds"]:.2f} s, peak RSS '
                f'{res["maxrss_mib"]:.0f} MiB')
    ratios = [j['seconds'] / e['seconds'] for j, e in zip(runs, regular)]
    figures.append(ratio_line(
        'P3', 'eval_jittered/eval_regular', ratios, '<=', 1.5, smoke=smoke,
        note=f'{messages} Imu msgs, stamps +-{JITTER_NS / 1e6:g} ms'))
    return runs


def _big(figures, log, baseline=None, small_rss=(), messages=None):
    """
    observer-eval and rosbags (a) on the 10^7-message bag: time and peak RSS.

    ``small_rss``: the peak RSS of the rounds' evaluations of the ``messages`` bag, that
    of 10^7 is compared with (its median).

    """
    big_n = 10_000_000
    big_bag = generate(big_n, log=log)
    with tempfile.TemporaryDirectory(prefix='p3_big_') as tmp:
        res = _run_worker('eval', big_bag, Path(tmp) / 'out')
        base_res = None
        if baseline:
            base_res = _run_worker('eval', big_bag, Path(tmp) / 'base', pythonpath=baseline)
    log(f'  P3 big: eval of {big_n} msgs: {res["seconds"]:.1f} s, peak RSS '
        f'{res["maxrss_mib"]:.0f} MiB')
    if base_res is not None:
        log(f'  P3 big: eval of {baseline}: {base_res["seconds"]:.1f} s, peak RSS '
            f'{base_res["maxrss_mib"]:.0f} MiB')
        _versus_baseline(figures, [res], [base_res], big_n, baseline)
    base = _run_worker('a', big_bag)
    log(f'  P3 big: rosbags (a) of {big_n} msgs: {base["seconds"]:.1f} s, peak RSS '
        f'{base["maxrss_mib"]:.0f} MiB')
    small = summary(small_rss)['median'] if small_rss else math.nan
    figures.append(ratio_line('P3', f'eval_peak_rss_1e7/eval_peak_rss[{messages}]',
                              [res['maxrss_mib'] / small], '<=', 1.1,
                              note=f'{res["maxrss_mib"]:.0f} MiB against {small:.0f} MiB '
                                   f'(median of the rounds), {res["seconds"]:.1f} s'))
    figures.append(ratio_line('P3', 'eval_peak_rss_1e7/400MiB',
                              [res['maxrss_mib'] / 400.0], '<=', 1.0,
                              note=f'{res["maxrss_mib"]:.0f} MiB'))
    figures.append(ratio_line('P3', 'eval_1e7/rosbags_read_deserialise_1e7',
                              [res['seconds'] / base['seconds']], '<=', 1.0,
                              note=f'rosbags {base["seconds"]:.1f} s, '
                                   f'{base["maxrss_mib"]:.0f} MiB'))
    return {'eval': res, 'a': base, 'baseline': base_res}


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ['--worker']:
        kind, args = argv[1], argv[2:]
        func = {'a': worker_a, 'b': worker_b, 'eval': worker_eval,
                'replay': worker_replay}[kind]
        res = func(*args)
        res['maxrss_mib'] = _maxrss_mib()
        print(json.dumps(res))
        return 0
    parser = common_parser(__doc__.splitlines()[1])
    parser.add_argument('--rounds', type=int, help='rounds of (eval, a, b); default 3')
    parser.add_argument('--messages', type=int, help='Imu messages in the bag (default 10^6)')
    parser.add_argument('--big', action='store_true',
                        help='also the 10^7-message bag: peak RSS within 1.1x of 10^6, < 400 MiB')
    parser.add_argument('--jitter', action='store_true',
                        help='also the bag with jittered stamps: within 1.5x of regular')
    parser.add_argument('--baseline-pythonpath', metavar='DIR',
                        help="also run this copy's observer-eval (an earlier version) "
                             'on the same bags: eval / its eval <= 1')
    args = parser.parse_args(argv)
    print('P3: observer-eval on a synthetic Imu bag', flush=True)
    return report(args.json, run(smoke=args.smoke, rounds=args.rounds, big=args.big,
                                 messages=args.messages, log=log, jitter=args.jitter,
                                 baseline=args.baseline_pythonpath))


if __name__ == '__main__':
    raise SystemExit(main())
