"""The README's and the user guide's shell blocks, run as written, in order, in one shell.

Every ```bash block of README.md, then of docs/user-guide.md, runs in one bash (`set -e`, so a
failing documented command fails the test), unless the line before its fence is a marker

    <!-- docs-test: skip: REASON -->

for what cannot run here (the rig, root, the `ros2` CLI of a full install, a server that runs
until stopped); a marker without a reason, or one not followed by a block, fails. The shell
runs in a scratch directory that links the repository's entries, so `runs/` lands there, on
the test's own ROS_DOMAIN_ID; background jobs the documents start are ended at the end.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest

from support.procs import ROOT, popen_in_own_group

pytestmark = pytest.mark.integration

DOCUMENTS = ('README.md', 'docs/user-guide.md')
MARKER = re.compile(r'^<!--\s*docs-test:\s*skip:\s*(?P<reason>.*?)\s*-->\s*$')
FENCE = re.compile(r'^```(?P<lang>\S*)')
PORT = Path('/tmp/pma0')        # the documents' simulated device
TIMEOUT_S = 420.0   # both documents' runnable blocks, in one shell, on a loaded machine


@dataclass(frozen=True)
class Block:
    document: str
    line: int          # of the opening fence, 1-based
    lang: str
    text: str
    skip: str | None   # the marker's reason


def blocks(document: str) -> list[Block]:
    lines = (ROOT / document).read_text(encoding='utf-8').splitlines()
    found, index = [], 0
    while index < len(lines):
        fence = FENCE.match(lines[index])
        if not fence:
            marker = MARKER.match(lines[index])
            if marker and not (index + 1 < len(lines) and FENCE.match(lines[index + 1])):
                raise AssertionError(f'{document}:{index + 1}: a docs-test marker must be the '
                                     'line right before a code fence')
            index += 1
            continue
        end = next(i for i in range(index + 1, len(lines)) if lines[i].startswith('```'))
        marker = MARKER.match(lines[index - 1]) if index else None
        found.append(Block(document, index + 1, fence['lang'],
                           '\n'.join(lines[index + 1:end]), marker['reason'] if marker else None))
        index = end + 1
    return found


def shell_blocks() -> list[Block]:
    return [b for doc in DOCUMENTS for b in blocks(doc) if b.lang in ('bash', 'sh', 'shell')]


def script(selected: list[Block]) -> str:
    # A command that fails ends the script; its background nodes end with it, so the failure
    # is reported at once (they held the output pipe open until the test's timeout).
    parts = ['set -e -o pipefail', "trap 'kill $(jobs -p) 2>/dev/null || true; wait' EXIT"]
    for block in selected:
        parts.append(f'echo "### {block.document}:{block.line} at ${{SECONDS}} s" >&2')
        parts.append(block.text)
    parts.append('echo "### all documented commands ran" >&2')
    return '\n'.join(parts) + '\n'


def run_script(text: str, cwd: Path, timeout_s: float) -> tuple[int, str]:
    """bash -c TEXT in its own process group; every process left in it ends with it."""
    proc = popen_in_own_group(['bash', '-c', text], cwd=cwd, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, text=True)
    try:
        out, _ = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        stuck = subprocess.run(['ps', '-o', 'pid,stat,wchan:20,etime,args', '-g', str(proc.pid)],
                               capture_output=True, text=True, check=False).stdout
        out = ''
        for sig in (signal.SIGTERM, signal.SIGKILL):
            os.killpg(proc.pid, sig)
            try:
                out, _ = proc.communicate(timeout=10)
                break
            except subprocess.TimeoutExpired as held:   # keep what it wrote up to here
                out = held.output.decode(errors='replace') if isinstance(held.output, bytes) \
                    else (held.output or '')
        out += f'\n### timed out after {timeout_s} s; its processes then:\n{stuck}'
    finally:
        for sig in (signal.SIGTERM, signal.SIGKILL):
            try:
                os.killpg(proc.pid, sig)
            except ProcessLookupError:
                break
    return proc.returncode, out


def scratch_checkout(tmp_path: Path) -> Path:
    """A directory whose entries are the repository's, without its runs/."""
    work = tmp_path / 'repo'
    work.mkdir()
    for entry in ROOT.iterdir():
        if entry.name not in ('runs', '.git'):
            (work / entry.name).symlink_to(entry)
    return work


def test_every_block_is_run_or_says_why_not():
    selected = shell_blocks()
    assert {b.document for b in selected} == set(DOCUMENTS)
    for block in selected:
        assert block.skip is None or len(block.skip) > 10, f'{block}: say why it is skipped'
    # What each document promises to run here: the ways without a full install.
    runnable = [b for b in selected if b.skip is None]
    for document in DOCUMENTS:
        text = '\n'.join(b.text for b in runnable if b.document == document)
        for needed in ('pma status', 'pma sweep', 'pma length', 'pma param set', 'refit'):
            assert needed in text, f'{document} runs no {needed!r}'
    for block in runnable:
        assert not re.search(r'^\s*ros2 ', block.text, re.MULTILINE), \
            f'{block.document}:{block.line} runs the ros2 CLI: mark it'
    for block in selected:
        assert not re.search(r'^\s*cd ', block.text, re.MULTILINE), \
            f'{block.document}:{block.line}: a bare cd leaves later lines elsewhere: a subshell'


def test_every_documented_pma_line_parses_even_where_it_is_not_run():
    """A `pma` line in a skipped block (it needs the rig, or runs long) still has flags that
    exist: the real argument parser reads every `pma ...` line of the docs and cli.md."""
    import shlex

    from pma_cli.main import parser

    documents = (*DOCUMENTS, 'docs/cli.md')
    lines = [(document, line.strip()) for document in documents for block in blocks(document)
             if block.lang in ('bash', 'sh', '') for line in block.text.splitlines()
             if line.strip().startswith('pma ')]
    assert len(lines) > 10
    for document, line in lines:
        command = re.sub(r'\s+#.*$', '', line).rstrip(' &\\')   # comment, `&`, continuation
        argv = shlex.split(command)[1:]
        argv = argv[:argv.index('&&')] if '&&' in argv else argv
        try:
            parser().parse_args(argv)
        except SystemExit:
            pytest.fail(f'{document}: `{line}` does not parse (pma {argv[0]} --help)')


STRAY_PARAMETER = re.compile(r'(?<!\S)-p\s+[\w.]+:=')


def logical_lines(text: str) -> list[str]:
    """Shell lines with their backslash continuations joined."""
    return re.sub(r'\\\n', ' ', text).splitlines()


def stray_parameters(text: str) -> list[str]:
    """Lines of a shell block that pass a ROS parameter (`-p name:=value`, comments too)
    with no --ros-args before it: rcl ignores it and the node runs on its default."""
    return [line for line in logical_lines(text)
            for match in STRAY_PARAMETER.finditer(line)
            if '--ros-args' not in line[:match.start()]]


def test_no_document_passes_a_parameter_without_ros_args():
    documents = ('README.md', *sorted(str(p.relative_to(ROOT))
                                      for p in (ROOT / 'docs').glob('*.md')))
    found = [(document, block.line, line) for document in documents
             for block in blocks(document) if block.lang in ('bash', 'sh', 'shell', '')
             for line in stray_parameters(block.text)]
    assert not found, f'-p without --ros-args (ignored by the node): {found}'
    # The check itself: what the README said, and what it says now.
    assert stray_parameters('pma run pma_bringup foxglove_live  # -p host:=0.0.0.0 for the lab')
    assert stray_parameters('foxglove_live \\\n  -p host:=0.0.0.0')
    assert not stray_parameters('foxglove_live --ros-args -p port:=8766 \\\n'
                                '    -p topics:="[a]"')


def test_a_failing_documented_command_fails_the_run(tmp_path):
    block = Block('x.md', 1, 'bash', 'true\nfalse\necho never', None)
    code, out = run_script(script([block]), tmp_path, 20)
    assert code != 0 and 'never' not in out and 'all documented commands ran' not in out


@pytest.mark.timeout(TIMEOUT_S + 60)   # its own limit first: it reports where the run was
@pytest.mark.slow
def test_the_documented_commands_run_in_order_in_one_shell(tmp_path):
    if PORT.exists():
        pytest.fail(f'{PORT} exists: another simulated rig runs here; the documents use it')
    runnable = [b for b in shell_blocks() if b.skip is None]
    work = scratch_checkout(tmp_path)
    code, out = run_script(script(runnable), work, TIMEOUT_S)
    last = [line for line in out.splitlines() if line.startswith('### ')][-1:]
    assert code == 0, f'failed in the block after {last}:\n{out[-6000:]}'
    assert out.rstrip().endswith('### all documented commands ran'), out[-3000:]
    # What the documents said would be there, is.
    runs = work / 'runs'
    assert (runs / 'day1' / 'metadata.yaml').exists()
    assert (runs / 'day1.csv').read_text().count('\n') > 100
    assert (runs / 'day1' / 'refit.yaml').exists()
    assert (runs / 'day2_recovered' / 'metadata.yaml').exists()
    assert (runs / 'sweep1' / 'refit.yaml').exists()
    assert not PORT.exists(), 'the documents left their simulated device running'
