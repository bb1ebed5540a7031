"""Every `rosrun` and `roslaunch` line that README.md shows in its code
blocks runs as written, finds exactly one file, and says nothing alarming.

Each line is run through `bash -c 'source env.bash && <line>'`, the way the
README tells a reader to, with its own ROS_HOME and a master on a free port
(so nothing clashes with another test or a roscore already running), and a
virtual X display (xvfb-run) for `rviz:=true`:

* `roslaunch` lines run for WINDOW seconds and then get SIGINT, like Ctrl-C.
  Every node the launch file names, and the nodes our nodes start
  themselves (robot_state_publisher, rviz, one firmware per arm), must
  resolve to one program only (`roslib.packages.find_node`, which roslaunch
  uses and which silently takes the first of several).  A catkin
  devel-space relay and the script it runs count as one program, and so do
  identical files (Debian's rviz is /usr/lib/rviz/rviz and, through a link,
  /usr/bin/rviz), as rosrun itself treats them; but one file found twice
  (a link loop, a copy of the package inside itself) fails.
* `rosrun` lines run while `both_arms.launch` runs (the README starts it
  first).  `rosrun ambots front_end` gets "5" (quit) on stdin: the menu must
  show its five choices and exit 0.  Each rosrun line runs a second time
  with `rosrun --debug`, which must name the one file it ran.

The output must not contain rosrun's chooser ("You have chosen a non-unique
executable ... please pick one"), find's "File system loop detected",
"Couldn't find executable", "cannot locate", "ERROR", "Traceback" or (without
--debug) any "[rosrun]" line, and no process may die early with an error.
Output after Ctrl-C is checked the same way (this test found a shutdown race
of the firmware node: its loop published after rospy had closed a topic).
Every process started here is stopped: process groups, and the nodes
roslaunch starts in their own sessions, found through /proc.

Needs the catkin workspace (`make setup`); `make test` runs it."""
import hashlib
import json
import os
import re
import shlex
import signal
import socket
import subprocess
import time

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
README = os.path.join(ROOT, "README.md")
ENV_BASH = os.path.join(ROOT, "env.bash")

#: how long a roslaunch line runs before it gets SIGINT (s)
WINDOW = 12.0
#: what an interactive node gets on stdin (the README line is the menu: 5 quits)
STDIN = {"front_end": "5\n"}
#: the menu the README promises (`rosrun ambots front_end`)
MENU = ("1) start demo", "2) slice an STL file", "3) send G-code to the arms", "4) start printing",
        "5) quit", "choice [1-5]:")
#: nodes that our nodes start at run time (roslaunch scriptapi, subprocess)
STARTED_BY = {("ambots", "cell"): [("robot_state_publisher", "robot_state_publisher"), ("rviz", "rviz")],
              ("ambots", "capture"): [("rviz", "rviz")]}
#: rosrun's chooser and search errors, find's loop warning, errors, crashes (case-sensitive)
BAD = ("You have chosen a non-unique executable", "please pick one", "File system loop detected",
       "Couldn't find executable", "cannot locate", "Cannot locate", "[rospack] Error: package", "ERROR",
       "Traceback", "process has died")
#: placeholders a runnable README line must not hold
PLACEHOLDERS = ("[", "]", "\u2026", "...", "<", ">")


# --- README --------------------------------------------------------------------------------------

def code_lines(text):
    """(line number, text) of every line inside a fenced code block."""
    out, fence = [], None
    for n, line in enumerate(text.splitlines(), 1):
        m = re.match(r"\s*(```+|~~~+)", line)
        if m and (fence is None or m.group(1).startswith(fence)):
            fence = None if fence else m.group(1)
        elif fence:
            out.append((n, line))
    return out


def command_of(line):
    """The command a code line shows: without a leading `$ ` prompt and a trailing `# comment`."""
    s = line.strip()
    if s.startswith("$ "):
        s = s[2:].lstrip()
    return re.sub(r"(^|\s)#.*$", "", s).strip()


def ros_lines(text):
    """(line number, command) of every rosrun / roslaunch line in the code blocks."""
    cmds = ((n, command_of(line)) for n, line in code_lines(text))
    return [(n, c) for n, c in cmds if c.split(" ", 1)[0] in ("rosrun", "roslaunch") and " " in c]


def placeholders(command):
    return [p for p in PLACEHOLDERS if p in command]


# --- output checks (pure functions, checked on real bad output below) ---------------------------

def problems(output, debug=False):
    """What is wrong in a line's output: alarming words, and "[rosrun]" lines unless --debug."""
    found = [b for b in BAD if b in output]
    if not debug and "[rosrun]" in output:
        found.append("[rosrun]")
    return found


def program_of(path):
    """What a found executable runs: the script a catkin devel-space relay execs, else the file
    itself; identified by real path and content (Debian ships rviz as two identical binaries)."""
    real = os.path.realpath(path)
    with open(real, "rb") as f:
        data = f.read()
    m = re.search(rb"generated from catkin/cmake/template/script\.py\.in.*?python_script = '([^']+)'", data, re.S)
    if m:
        return program_of(m.group(1).decode())
    return hashlib.sha1(data).hexdigest()


def distinct_programs(paths):
    """How many different programs the executables found for one node type are."""
    return len({program_of(p) for p in paths})


def found_twice(paths):
    """Paths that are the same file found again (through a link loop or a copy of the package
    inside itself, as the old in-package workspace was)."""
    seen, twice = {}, []
    for p in paths:
        real = os.path.realpath(p)
        if real in seen:
            twice.append((seen[real], p))
        seen.setdefault(real, p)
    return twice


def ran_files(debug_output):
    """The files `rosrun --debug` says it ran ("[rosrun] Running <prefix> <path> <args>")."""
    return [m.group(1) for m in re.finditer(r"^\[rosrun\] Running\s+(\S+)", debug_output, re.M)]


# --- processes ----------------------------------------------------------------------------------

def free_port():
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _proc_table():
    """{pid: (ppid, start time)} of every process."""
    table = {}
    for name in os.listdir("/proc"):
        if name.isdigit():
            try:
                with open("/proc/%s/stat" % name) as f:
                    fields = f.read().rsplit(")", 1)[1].split()
                table[int(name)] = (int(fields[1]), fields[19])
            except (OSError, IndexError):
                pass
    return table


def descendants(pid):
    """{pid: start time} of every process below ``pid`` (roslaunch puts its nodes in new sessions)."""
    table = _proc_table()
    children = {}
    for p, (ppid, _) in table.items():
        children.setdefault(ppid, []).append(p)
    out, todo = {}, list(children.get(pid, []))
    while todo:
        p = todo.pop()
        out[p] = table[p][1]
        todo.extend(children.get(p, []))
    return out


def kill_all(proc, known, sig=signal.SIGKILL):
    """Signal ``proc``'s group and every process in ``known`` ({pid: start time}) still alive."""
    try:
        os.killpg(proc.pid, sig)
    except ProcessLookupError:
        pass
    table = _proc_table()
    for pid, start in known.items():
        if table.get(pid, (None, None))[1] == start:      # the same process, not a reused pid
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass


class Run:
    """One README line, run by bash after `source env.bash`; output in ``log``."""

    def __init__(self, command, env, log, stdin_text=None):
        self.command, self.log = command, log
        self.known = {}
        self.stopped_at = None              #: size of the log when Ctrl-C was sent
        with open(log, "w") as f:           # a file, not a pipe: a stray grandchild must not hang us
            self.proc = subprocess.Popen(
                ["bash", "-c", "source %s && %s" % (shlex.quote(ENV_BASH), command)], cwd=ROOT, env=env,
                stdin=subprocess.PIPE if stdin_text is not None else subprocess.DEVNULL,
                stdout=f, stderr=subprocess.STDOUT, text=True, start_new_session=True)
        if stdin_text is not None:
            self.proc.stdin.write(stdin_text)
            self.proc.stdin.close()

    def remember(self):
        self.known.update(descendants(self.proc.pid))

    def run_for(self, seconds):
        """Let it run ``seconds`` (or until it ends); then Ctrl-C.  The exit status if it ended first."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline and self.proc.poll() is None:
            self.remember()
            time.sleep(0.5)
        early = self.proc.poll()
        self.stop()
        return early

    def wait(self, timeout):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and self.proc.poll() is None:
            self.remember()
            time.sleep(0.2)
        if self.proc.poll() is None:
            self.stop()
            return None
        return self.proc.returncode

    def stop(self):
        """Ctrl-C: SIGINT to the line's process group (roslaunch then stops its nodes, which run in
        sessions of their own); then SIGINT and SIGKILL to whatever is left of it."""
        self.remember()
        if self.stopped_at is None:
            self.stopped_at = os.path.getsize(self.log)
        kill_all(self.proc, {}, signal.SIGINT)
        try:
            self.proc.wait(20)
        except subprocess.TimeoutExpired:
            pass
        for sig, grace in ((signal.SIGINT, 10), (signal.SIGKILL, 5)):
            left = {p: s for p, s in self.known.items() if _proc_table().get(p, (None, None))[1] == s}
            if not left and self.proc.poll() is not None:
                break
            kill_all(self.proc, left, sig)
            deadline = time.monotonic() + grace
            while time.monotonic() < deadline and any(
                    _proc_table().get(p, (None, None))[1] == s for p, s in left.items()):
                time.sleep(0.2)
        self.proc.wait(10)

    @property
    def output(self):
        with open(self.log, errors="replace") as f:
            return f.read()

    @property
    def output_before_stop(self):
        with open(self.log, "rb") as f:
            return f.read(self.stopped_at).decode(errors="replace")

    @property
    def output_after_stop(self):
        with open(self.log, "rb") as f:
            f.seek(self.stopped_at or 0)
            return f.read().decode(errors="replace")


def ros_env(tmp_path, display):
    return dict(os.environ, ROS_HOME=str(tmp_path / "ros_home"),
                ROS_MASTER_URI="http://localhost:%d" % free_port(), **display)


# --- fixtures -----------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def display():
    """A virtual X screen for rviz:=true: xvfb-run holds one open while its child sleeps.
    {DISPLAY, XAUTHORITY} for the environment."""
    with open(os.devnull, "w") as null:
        screen = subprocess.Popen(["xvfb-run", "-a", "-s", "-screen 0 1280x800x24 -nolisten tcp",
                                   "bash", "-c", 'echo "$DISPLAY $XAUTHORITY"; exec sleep 3600'],
                                  stdout=subprocess.PIPE, stderr=null, text=True, start_new_session=True)
    words = screen.stdout.readline().split()
    assert len(words) == 2 and words[0].startswith(":"), "xvfb-run did not start"
    yield {"DISPLAY": words[0], "XAUTHORITY": words[1]}
    os.killpg(screen.pid, signal.SIGTERM)
    screen.wait(10)
    screen.stdout.close()


@pytest.fixture(scope="module")
def running_cell(tmp_path_factory, display):
    """`roslaunch ambots both_arms.launch` running (the README starts it before `rosrun`): the env."""
    tmp = tmp_path_factory.mktemp("running_cell")
    env = ros_env(tmp, display)
    run = Run("roslaunch ambots both_arms.launch", env, str(tmp / "both_arms.log"))
    try:
        import rosgraph
        master = rosgraph.Master("/test_readme", master_uri=env["ROS_MASTER_URI"])
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            assert run.proc.poll() is None, run.output[-3000:]
            run.remember()
            try:
                _pubs, subs, _srvs = master.getSystemState()
                if any(t == "/ambots/communication_hub_topic" and "/communication_hub" in nodes
                       for t, nodes in subs):
                    break
            except Exception:        # no master yet
                pass
            time.sleep(0.5)
        else:
            pytest.fail("the hub did not come up within 60 s:\n" + run.output[-3000:])
        yield env
    finally:
        run.stop()


# --- the README's lines -------------------------------------------------------------------------

with open(README) as _f:
    LINES = ros_lines(_f.read())
ROSRUN = [c for _, c in LINES if c.startswith("rosrun ")]
ROSLAUNCH = [c for _, c in LINES if c.startswith("roslaunch ")]


def test_the_readme_shows_ros_lines_without_placeholders():
    assert "rosrun ambots front_end" in ROSRUN, LINES
    assert ROSLAUNCH, LINES
    bad = [(n, c, placeholders(c)) for n, c in LINES if placeholders(c)]
    assert not bad, "README.md: write runnable lines, options go in prose or a table: %s" % bad


def test_readme_commands_have_no_placeholders():
    """Every command the README shows (make, python, source, ros*) is runnable as written."""
    text = open(README).read()
    bad = []
    for n, line in code_lines(text):
        c = command_of(line)
        if c.split(" ", 1)[0] in ("make", "python", "source", "rosrun", "roslaunch", ".venv/bin/python") \
                and placeholders(c):
            bad.append((n, c))
    assert not bad, bad


def unique_nodes(command, env):
    """{pkg/type: [files]} for every node the roslaunch line starts, as find_node resolves them
    (roslaunch runs the first of several files without a word)."""
    code = r"""
import json, shlex, sys
import roslaunch.config, roslaunch.rlutil, roslib.packages
words = shlex.split(sys.argv[1])[1:]
started_by = {tuple(k.split("/")): v for k, v in json.loads(sys.argv[2]).items()}
files = [w for w in words if ":=" not in w and not w.startswith("-")]
args = [w for w in words if ":=" in w]
paths = roslaunch.rlutil.resolve_launch_arguments(files)
sys.argv = ["roslaunch"] + files + args
config = roslaunch.config.load_config_default(paths, None, verbose=False)
types = {(n.package, n.type) for n in config.nodes}
for t in list(types):
    types.update(tuple(x) for x in started_by.get(t, []))
print(json.dumps({"%s/%s" % t: roslib.packages.find_node(*t) for t in sorted(types)}))
"""
    started_by = json.dumps({"%s/%s" % k: v for k, v in STARTED_BY.items()})
    r = subprocess.run(["bash", "-c", 'source %s && python -c "$0" "$1" "$2"' % shlex.quote(ENV_BASH),
                        code, command, started_by], cwd=ROOT, env=env, capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("command", ROSLAUNCH)
def test_roslaunch_line_runs_and_every_node_is_one_file(command, tmp_path, display):
    env = ros_env(tmp_path, display)
    nodes = unique_nodes(command, env)
    assert nodes and all(distinct_programs(files) == 1 for files in nodes.values()), nodes
    assert not any(found_twice(files) for files in nodes.values()), nodes
    run = Run(command, env, str(tmp_path / "launch.log"))
    early = run.run_for(WINDOW)
    out = run.output
    assert early is None, "ended after less than %.0f s with status %s:\n%s" % (WINDOW, early, out[-4000:])
    assert "process[" in out and "started with pid" in out, out[-4000:]
    running = run.output_before_stop
    assert not problems(running), (problems(running), running[-4000:])
    stopping = run.output_after_stop            # after Ctrl-C
    assert not problems(stopping), ("after Ctrl-C", problems(stopping), stopping[-4000:])


@pytest.mark.parametrize("command", ROSRUN)
def test_rosrun_line_runs_one_file(command, tmp_path, running_cell):
    words = command.split()
    node = words[2]
    for debug in (False, True):
        line = " ".join(words[:1] + ["--debug"] + words[1:]) if debug else command
        run = Run(line, running_cell, str(tmp_path / ("debug.log" if debug else "run.log")), STDIN.get(node))
        status = run.wait(45) if node in STDIN else run.run_for(WINDOW)
        out = run.output
        assert status in (0, None), "%s: exit status %s:\n%s" % (line, status, out[-4000:])
        assert not problems(out, debug), (line, problems(out, debug), out[-4000:])
        if debug:
            files = ran_files(out)
            assert len(files) == 1 and os.access(files[0], os.X_OK), (files, out[-4000:])
            assert os.path.basename(files[0]) == node, files
        if node == "front_end":           # the menu itself, no chooser before it
            assert status == 0, out
            for choice in MENU:
                assert choice in out, (choice, out)


# --- the checks catch what they are for (a real chooser and link loop, in a throw-away package) ---

def test_the_checks_catch_a_chooser_and_a_link_loop(tmp_path):
    pkg = tmp_path / "readme_probe"
    for sub in ("a", "b"):
        (pkg / sub).mkdir(parents=True)
        (pkg / sub / "probe").write_text("#!/bin/sh\necho probe\n")
        (pkg / sub / "probe").chmod(0o755)
    (pkg / "package.xml").write_text(
        '<package format="2"><name>readme_probe</name><version>0.0.0</version><description>x</description>'
        '<maintainer email="x@example.com">x</maintainer><license>BSD</license></package>\n')
    (pkg / "loop").symlink_to("..")
    env = dict(os.environ, ROS_HOME=str(tmp_path / "ros_home"))
    # after `source env.bash`, which sets ROS_PACKAGE_PATH to the workspace's
    run = Run("export ROS_PACKAGE_PATH=%s:$ROS_PACKAGE_PATH && rosrun readme_probe probe" % tmp_path, env,
              str(tmp_path / "probe.log"))
    run.wait(30)
    out = run.output
    found = problems(out)
    for needle in ("You have chosen a non-unique executable", "please pick one", "File system loop detected",
                   "[rosrun]"):
        assert needle in found, (needle, found, out)
    assert problems("[rosrun] Couldn't find executable named capture below /x") != []
    assert problems("[rospack] Error: package 'ambots' not found") != []
    assert ran_files("[rosrun] Running  /ws/devel/lib/ambots/front_end --help\n") == [
        "/ws/devel/lib/ambots/front_end"]
    assert ran_files(out) == []                    # the chooser runs nothing
    (pkg / "b" / "probe").write_text("#!/bin/sh\necho another probe\n")
    assert distinct_programs([str(pkg / "a" / "probe"), str(pkg / "b" / "probe")]) == 2
    assert distinct_programs([str(pkg / "a" / "probe"), str(pkg / "loop" / "readme_probe" / "a" / "probe")]) == 1
    assert found_twice([str(pkg / "a" / "probe"), str(pkg / "loop" / "readme_probe" / "a" / "probe")])
    assert not found_twice(["/usr/lib/rviz/rviz", "/usr/share/rviz/rviz"])
    assert placeholders("roslaunch ambots both_arms.launch [cell:=\u2026]")
    assert not placeholders("roslaunch ambots both_arms.launch speed:=10 rviz:=true")


with open(README) as _f:
    CTL = [c for _, c in ((n, command_of(line)) for n, line in code_lines(_f.read()))
           if c.startswith("python -m ambots ctl")]


def test_the_readme_shows_the_ctl_tool():
    assert "python -m ambots ctl pause" in CTL and "python -m ambots ctl resume" in CTL, CTL


@pytest.mark.parametrize("command", CTL)
def test_ctl_line_runs_against_the_running_cell(command, tmp_path, running_cell):
    """`python -m ambots ctl ...` with `both_arms.launch` running (idle arms
    have nothing to obey: the tool says so and exits 0; a live print is
    paused, stopped and resumed in test_faults.py)."""
    run = Run(command, running_cell, str(tmp_path / "ctl.log"))
    status = run.wait(60)
    out = run.output
    assert status == 0, out[-3000:]
    assert " sent to kinova (R0), ur10 (R1)" in out and "kinova IDLE; ur10 IDLE" in out, out[-3000:]
    assert not problems(out), (problems(out), out[-3000:])
