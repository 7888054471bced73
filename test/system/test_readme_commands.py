# Every shell command the user documentation shows, run as a user types it.
"""
The fenced shell blocks of README.md and docs/*.md, run as written on the shipped files.

Each block whose info string is ``sh``, ``bash``, ``shell`` or ``console`` is one test:
its commands run one after the other with ``bash``, in a scratch copy of the repository
(``config/``, ``bags/samples/`` and the rest linked or copied, ``.venv/bin`` first on
PATH as for a user who activated the environment, this test process's ROS_DOMAIN_ID), and
each must exit 0 and print the verdict its program prints on success (``VERDICTS``; a
command whose program has none here fails the test until one is added).

What is changed, and only where the command allows it: a closed-loop run
(``observer-run``, ``make demo``) that does not give ``simulator.duration`` itself gets a
short one (``-p simulator.duration:=8.0``; ``make demo ARGS=...``). A bag a command reads
that no command of its block records is made first (``BAGS``).

A block, or some of its commands, that must not run here is marked in the Markdown file
by an HTML comment on the line just before the block's opening fence (invisible on the
rendered page):

    <!-- not run: REASON -->                    the whole block
    <!-- not run `PREFIX`: REASON -->           its commands that begin with PREFIX

(several ``not run `PREFIX`:`` marks may share one comment, separated by ``;``). REASON
says why, and what runs the command instead where something does (``make test`` is
this suite; the real-install block is run by test/test_ros2cli.py after colcon build).

"""

import os
from pathlib import Path
import re
import shlex
import shutil
import subprocess

from bag_synth import simulate, write_bag
from observer_ros.vehicle import load_vehicle
import pytest
from ros_helpers import DOMAIN_ID, REPO

DOCS = [REPO / 'README.md'] + sorted((REPO / 'docs').glob('*.md'))
SHELLS = ('sh', 'bash', 'shell', 'console')
DURATION = 8.0          # s simulated: a closed-loop run whose command does not set one
TIMEOUT = 1200.0        # s per command: a loaded 2-core machine, a run and its evaluation
MARK = re.compile(r'<!--\s*(not run.*?)-->', re.S)
SKIP = re.compile(r'not run(?:\s+`([^`]+)`)?\s*:\s*([^;]+)')


def parse_blocks(path, root=REPO):
    """
    Return the fenced shell blocks of a Markdown file.

    Returns
    -------
    list of dict
        ``file``, ``line`` (of the opening fence), ``commands`` (each a logical line,
        continuation lines joined, with the line it starts on) and ``skip``: ``{PREFIX:
        reason}`` with ``''`` for the whole block.

    """
    lines = Path(path).read_text().splitlines()
    blocks, i = [], 0
    while i < len(lines):
        fence = re.match(r'^(```+|~~~+)\s*(\S*)', lines[i])
        if not fence:
            i += 1
            continue
        opening, lang, start = fence.group(1), fence.group(2), i
        body = []
        i += 1
        while i < len(lines) and not lines[i].startswith(opening):
            body.append((i + 1, lines[i]))
            i += 1
        i += 1
        if lang not in SHELLS:
            continue
        skip = {}
        before = lines[start - 1] if start else ''
        mark = MARK.search(before)
        if mark:
            for prefix, reason in SKIP.findall(mark.group(1)):
                skip[prefix.strip()] = reason.strip()
        blocks.append({'file': Path(path).relative_to(root).as_posix(), 'line': start + 1,
                       'commands': _logical_lines(body), 'skip': skip})
    return blocks


def _logical_lines(body):
    """Join continuation lines; drop blank lines and whole-line comments."""
    commands, pending, first = [], '', None
    for number, text in body:
        if not pending and (not text.strip() or text.lstrip().startswith('#')):
            continue
        first = number if not pending else first
        if text.rstrip().endswith('\\'):
            pending += text.rstrip()[:-1] + ' '
            continue
        commands.append((first, ' '.join((pending + text).split())))
        pending = ''
    if pending:
        commands.append((first, ' '.join(pending.split())))
    return commands


def _skipped(block, command):
    """Return the reason a command is marked not to run, or None."""
    for prefix, reason in block['skip'].items():
        if not prefix or command.startswith(prefix):
            return reason
    return None


BLOCKS = [b for path in DOCS for b in parse_blocks(path)]
RUN = [b for b in BLOCKS if any(_skipped(b, c) is None for _, c in b['commands'])]


def _words(command):
    """Return the command's words, its trailing comment left out."""
    return shlex.split(command, comments=True)


def program(command):
    """Return the program a command line runs: ``make demo`` or its first word."""
    words = _words(command)
    if words[:2] == ['make', 'demo']:
        return 'make demo'
    return words[0] if words else ''


def shortened(command):
    """
    Return the command with a short ``simulator.duration`` where the command allows one.

    ``observer-run`` takes ``-p``; ``make demo`` passes ``ARGS`` on to it. A command that
    sets the duration itself is run as it is.
    """
    if 'simulator.duration' in command:
        return command
    words = _words(command)
    if program(command) == 'make demo':
        return shlex.join(words + [f'ARGS=-p simulator.duration:={DURATION}'])
    if program(command) == 'observer-run':
        return shlex.join(words + ['-p', f'simulator.duration:={DURATION}'])
    return command


def _run_verdict(out, command):
    """observer-run: a verdict for every state, none diverging, nothing FAILED."""
    assert 'FAILED' not in out, out[-3000:]
    verdicts = re.findall(r'^\s+\S+: final .*?  (settled \(2%\) after [0-9.]+ s|not settled: '
                          r'.*|DIVERGING.*)$', out, re.M)
    assert verdicts and not any(v.startswith('DIVERGING') for v in verdicts), out[-3000:]
    if '--evaluate' in command or program(command) == 'make demo':
        assert "what the seeds' lessons look like on this run:" in out, out[-3000:]


def _tune_verdict(out, command):
    """observer-tune: the identified noise and the new vehicle file."""
    assert re.search(r'^tuned vehicle file: \S+_tuned\.yaml$', out, re.M), out[-3000:]
    assert re.search(r'^written to \S+_tune/ ', out, re.M), out[-3000:]


def _eval_verdict(out, command):
    """observer-eval: the comparison table and where its files went."""
    assert re.search(r'^variant\s', out, re.M), out[-3000:]
    assert re.search(r'^written to \S+ \(results\.txt, ', out, re.M), out[-3000:]


def _design_verdict(out, command):
    if '--robust' in command:
        assert 'written: ' in out, out[-3000:]          # the new vehicle file
    else:
        assert 'observable' in out, out[-3000:]


VERDICTS = {
    'make demo': _run_verdict,
    'observer-run': _run_verdict,
    'observer-tune': _tune_verdict,
    'observer-eval': _eval_verdict,
    'observer-design': _design_verdict,
}


def _submarine_noisy_bag(path):
    """Write a 4000-step submarine run with input noise of intensity 0.02^2 (tuning's input)."""
    vehicle = load_vehicle(str(REPO / 'config' / 'submarine.yaml'))
    run = simulate(vehicle, steps=4000, noise=True, seed=3,
                   process_noise=(vehicle.plant.B, [[0.02 ** 2]]))
    write_bag(path, run['messages'])


# Bags a command reads that the README's reader records on their own vehicle.
BAGS = {'bags/runs/sub1': _submarine_noisy_bag}


@pytest.fixture
def workdir(tmp_path):
    """Make a scratch repository: the checkout's files linked, bags/samples copied."""
    # its .venv is the checkout's: a `make` there that found the set-up out of date would
    # install the package from the scratch copy, which is deleted after the run
    stale = subprocess.run(['make', '-q', 'setup'], cwd=REPO, capture_output=True)
    if stale.returncode != 0:
        pytest.fail('the set-up (.venv) is older than the Makefile, setup.py or '
                    'requirements.txt: run `make setup` in the checkout first', pytrace=False)
    work = tmp_path / 'repo'
    work.mkdir()
    for entry in REPO.iterdir():
        if entry.name in ('bags', '.git') or entry.name.endswith('_logs'):
            continue
        (work / entry.name).symlink_to(entry)
    (work / 'bags').mkdir()
    shutil.copytree(REPO / 'bags' / 'samples', work / 'bags' / 'samples',
                    ignore=shutil.ignore_patterns('*_eval', '*_tune', '*_logs'))
    return work


def _env():
    env = dict(os.environ)
    env['PATH'] = f'{REPO / ".venv" / "bin"}{os.pathsep}{env.get("PATH", "")}'
    env['ROS_DOMAIN_ID'] = str(DOMAIN_ID)
    env['PYTHONUNBUFFERED'] = '1'
    return env


def test_the_docs_have_shell_blocks_and_every_mark_names_a_reason():
    files = {b['file'] for b in BLOCKS}
    assert 'README.md' in files, files
    for block in BLOCKS:
        for prefix, reason in block['skip'].items():
            assert reason, f'{block["file"]}:{block["line"]}: a mark without a reason'
            if prefix:
                assert any(c.startswith(prefix) for _, c in block['commands']), \
                    f'{block["file"]}:{block["line"]}: no command begins with {prefix!r}'


def test_the_parser_reads_marks_and_continuations(tmp_path):
    doc = tmp_path / 'x.md'
    doc.write_text('text\n<!-- not run `make test`: the suite itself -->\n```sh\n'
                   'make demo    # runs\nmake test\n\n# a comment\nobserver-eval a \\\n'
                   '    --vehicle b\n```\n```\nnot shell\n```\n<!-- not run: why -->\n'
                   '```bash\nfoo\n```\n')
    one, two = parse_blocks(doc, tmp_path)
    assert one['commands'] == [(4, 'make demo # runs'), (5, 'make test'),
                               (8, 'observer-eval a --vehicle b')]
    assert one['skip'] == {'make test': 'the suite itself'}
    assert _skipped(one, 'make test') and not _skipped(one, 'make demo # runs')
    assert two['skip'] == {'': 'why'} and _skipped(two, 'foo') == 'why'
    assert shortened('make demo VEHICLE=config/x.yaml  # c') == \
        "make demo VEHICLE=config/x.yaml 'ARGS=-p simulator.duration:=8.0'"
    assert shortened('observer-run a.yaml --evaluate').endswith(
        '-p simulator.duration:=8.0')
    assert shortened('observer-run a.yaml -p simulator.duration:=500.0') == \
        'observer-run a.yaml -p simulator.duration:=500.0'


@pytest.mark.ros
@pytest.mark.parametrize('block', RUN, ids=[f'{b["file"]}:{b["line"]}' for b in RUN])
def test_documented_commands_run_as_written(block, workdir):
    runnable = [(line, c) for line, c in block['commands'] if _skipped(block, c) is None]
    text = ' '.join(c for _, c in runnable)
    for bag, make in BAGS.items():
        if bag in text and not any(f'--out {bag}' in c for _, c in runnable):
            make(workdir / bag)
    for line, command in runnable:
        where = f'{block["file"]}:{line}: {command}'
        verdict = VERDICTS.get(program(command))
        assert verdict is not None, (
            f'{where}: no verdict known for {program(command)!r}: add one to VERDICTS in '
            f'{Path(__file__).name}, or mark the command not run (see its docstring)')
        result = subprocess.run(['bash', '-c', shortened(command)], cwd=workdir, env=_env(),
                                capture_output=True, text=True, timeout=TIMEOUT)
        out = result.stdout + result.stderr
        assert result.returncode == 0, f'{where}: exit {result.returncode}\n{out[-4000:]}'
        try:
            verdict(out, command)
        except AssertionError as err:
            raise AssertionError(f'{where}: {err}') from None
