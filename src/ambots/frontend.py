"""The front end: the operator's menu, and a whole print job for scripts.

The menu of the original design, same five choices in the same order::

    1) start demo (cut, slice, send and start the demo block)
    2) slice an STL file
    3) send G-code to the arms
    4) start printing
    5) quit

- 1 = 2 + 3 + 4 on :data:`ambots.job.DEMO_MODEL`.
- 2 asks for a model file (default: ``--model``), runs the job pipeline
  (:func:`ambots.job.run_job`) and writes ``DIR/<arm>.gcode``, ``<arm>.stl``
  and ``job.json`` (:func:`ambots.job.write_job`; ``DIR`` = ``--out``, else
  ``out/<model stem>``).  The job stays in memory for 3 and 4.
  1 and 2 slice with the menu's ``slicer``: ``builtin``, ``prusa`` or
  ``auto`` (:func:`ambots.slicer.choose_backend`: PrusaSlicer where
  ``prusa-slicer`` is installed, as the original did, else the built-in
  slicer; the command line's default for the menu), and say which one and
  why (``slicer: PrusaSlicer 2.5.0 (/usr/bin/prusa-slicer); --slicer auto:
  prusa-slicer is installed``) before slicing.
- 3 sends each arm its whole program as one A5 chunk
  (:class:`ambots.protocol.LoadChunk`) through the hub and waits until the
  hub has acknowledged every chunk.  Without a job in memory it asks for a
  directory and loads, for every arm of the cell, ``<arm>.gcode`` (as 2
  writes them) or ``<robot id>.gcode`` (as the original named them, e.g.
  ``1.gcode``; the ids are the cell's), whichever is there (both: refused)
  (checked: readable G-code, well-formed ``;@`` directives for this cell's
  arms, no bare A-series line).
- 4 sends A1 (:class:`ambots.protocol.Start`) to every arm whose program has
  ``start_first`` (in ``sequential`` mode only the first arm: the arms
  start each other with ``;@A1`` directives), then follows the arms' A10
  statuses, printing a line per arm when its state or its percentage (in
  steps of 10) changes, until every arm of the job is DONE (success), or an
  arm of the job reports ERROR or an A11 (failure: the error text, its
  G-code line number and that line of the arm's program), or the timeout
  (``--timeout``; none in the menu).  In the menu Ctrl-C stops *following*
  (the arms go on) and returns to the menu; while it follows, a typed line
  ``p``, ``s`` or ``r`` [arm] pauses (A2, end of line), stops (A12, brakes
  at once, resumable) or resumes (A6) every arm of the cell or the one named
  (:mod:`ambots.control`).  G-code not sent yet is sent
  first.  The first start of the programs sent names their chunk
  (``A1 R<id> C<chunk>``: an arm starts a chunk once) and is recorded in
  their directory (:data:`START_RECORD`); a front end started with
  ``--follow DIR`` to replace a crashed one sends that start again, so a
  start lost with the crashed front end (and a hub that had not yet
  acknowledged it) is not lost for good; an arm that has started ignores
  it.  A later 4 sends a plain A1, as the original did (a DONE arm runs
  its program again).
- 5, end of input (Ctrl-D) or Ctrl-C at the prompt: quit.

A bad answer gets one line saying what is expected, then the menu again.
A bad model, file or cell (:class:`ambots.errors.AmbotsError`) or an
``OSError`` is one line ``error: ...``, never a traceback, and the menu goes
on.  :meth:`Menu.print_job` (``--print``) runs 2 + 3 + 4 once and returns
the exit status: 0 every arm DONE, 1 failure (arm error, undeliverable
message, timeout; the reason on the error stream), 2 a bad model or cell.

The menu talks to the arms through a *link* (``send(message)``,
``poll()``, ``wait(timeout)``, ``pending()``); :class:`ReliableLink` is the
real one, ROS-free: it numbers the front end's messages (``S1000 Q...``,
:class:`ambots.reliable.Sender`, first Q from the wall clock), retries them
until the hub acknowledges them (:meth:`ReliableLink.tick`, called on a
timer), and acknowledges (A8 to the hub) and deduplicates what the hub
forwards (:class:`ambots.reliable.Receiver`).  The ROS layer
(``ambots.ros.front_end``) only moves its strings.
"""
import argparse
import functools
import itertools
import json
import os
import re
import threading
import time
from collections import deque
from dataclasses import dataclass

from ambots import data_path, topics
from ambots.errors import AmbotsError, GCodeError, ProtocolError
from ambots.protocol import (HUB, MAX_U32, Ack, ArmState, ErrorReport, LoadChunk, Start, Status,
                             WaitFor, decode, encode)
from ambots.reliable import Receiver, Sender, seq_seed

__all__ = ["CHOICES", "EXIT_OK", "EXIT_FAILED", "EXIT_BAD_INPUT", "Undelivered", "ReliableLink",
           "JobTracker", "Menu", "START_RECORD", "program_file_names", "program_files", "load_programs", "build_parser",
           "one_line"]

#: the menu, in the original's order
CHOICES = (
    ("1", "start demo (cut, slice, send and start the demo block)"),
    ("2", "slice an STL file"),
    ("3", "send G-code to the arms"),
    ("4", "start printing"),
    ("5", "quit"),
)
EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT = 0, 1, 2
#: --print without --timeout waits this long plus twice the longest estimated print time (s)
DEFAULT_TIMEOUT_BASE_S = 600.0
#: how long the menu waits for the hub's acknowledgements before saying so (s)
DEFAULT_ACK_TIMEOUT_S = 10.0
#: in the programs' directory: the chunk id last sent and the arms given its A1
#: (JSON), so a front end that replaces a crashed one can send that start again
START_RECORD = "start.json"


def print_timeout_s(print_time_s, speed=None):
    """How long a whole ``--print`` job may take by default, wall s:
    :data:`DEFAULT_TIMEOUT_BASE_S` plus twice the estimated print time
    (simulated s) at the pace of the cell's clock, ``speed`` simulated s per
    wall s (None: ``speed:=max`` or a real cell, counted as 1, so a slow
    machine is never cut short).  At ``speed:=4`` the demo's 9,055 s get
    600 + 2 x 9,055 / 4 s."""
    return DEFAULT_TIMEOUT_BASE_S + 2.0 * float(print_time_s) / (speed if speed else 1.0)


def one_line(exc, limit=400):
    """An error as one line (multi-line messages, e.g. a slicer's output,
    joined with " / "), cut to about ``limit`` characters."""
    text = " / ".join(line.strip() for line in str(exc).splitlines() if line.strip())
    if isinstance(exc, OSError) and exc.strerror:
        text = "%s: %s" % (exc.filename, exc.strerror) if exc.filename else exc.strerror
    return text if len(text) <= limit else text[:limit] + "..."


# ------------------------------------------------------------------- the link

@dataclass(frozen=True)
class Undelivered:
    """The link gave up a message: the hub never acknowledged it."""
    text: str       #: the message as last transmitted
    tries: int


class ReliableLink:
    """The front end's end of reliable delivery, without ROS.

    ``transmit(text)`` publishes one string to the hub (the caller's
    transport); the transport calls :meth:`receive_text` with every string
    that arrives in the front end's inbox and :meth:`tick` periodically
    (every 50 ms, say) for retransmissions.  ``clock()`` (s) times the
    retries.  Thread-safe: the transport may call in from other threads than
    the menu's.  Retries: ``initial_timeout`` s, times ``backoff`` after
    every try up to ``max_timeout``; after ``max_tries`` an
    :class:`Undelivered` note is queued for :meth:`poll` (None: forever).
    """

    def __init__(self, transmit, clock=time.monotonic, first_seq=None, initial_timeout=0.2,
                 backoff=2.0, max_timeout=2.0, max_tries=30, inbox_limit=10000):
        self._transmit = transmit
        self.clock = clock
        if first_seq is None:
            first_seq = seq_seed(time.time())
        self.sender = Sender(topics.FRONT_END_ID, first_seq, initial_timeout, backoff, max_timeout,
                             max_tries)
        self.receiver = Receiver(topics.FRONT_END_ID)
        self._cv = threading.Condition()
        self._inbox = deque(maxlen=inbox_limit)
        #: the last texts that could not be decoded, with the reason (not acknowledged)
        self.malformed = deque(maxlen=100)

    def send(self, message):
        """Number ``message`` (S1000, next Q), transmit it now and keep it
        until the hub acknowledges it.  Returns its Q."""
        with self._cv:
            out = self.sender.send(message, HUB, self.clock())
        self._transmit(encode(out.message))
        return out.seq

    def receive_text(self, text):
        """One string from the front end's inbox: an A8 settles one of our
        messages; anything numbered is acknowledged (A8 back to its sender,
        the hub) and, the first time only, queued for :meth:`poll`."""
        try:
            msg = decode(text)
        except ProtocolError as exc:
            self.malformed.append((text, exc.message))
            return
        if isinstance(msg, Ack):
            with self._cv:
                self.sender.acknowledge(msg)
                self._cv.notify_all()
            return
        with self._cv:
            deliveries = self.receiver.deliver(msg)
            for m, delivery in deliveries:
                if delivery.execute:
                    self._inbox.append(m)
            self._cv.notify_all()
        for _, delivery in deliveries:
            if delivery.ack is not None:
                self._transmit(encode(delivery.ack))

    def tick(self):
        """Transmit again what is due; queue an :class:`Undelivered` for
        each message given up."""
        given_up = []
        with self._cv:
            due = self.sender.due(self.clock(), on_give_up=given_up.append)
            for out in given_up:
                self._inbox.append(Undelivered(encode(out.message), out.tries))
            if given_up:
                self._cv.notify_all()
        for out in due:
            self._transmit(encode(out.message))

    def pending(self):
        """How many of our messages the hub has not acknowledged yet."""
        with self._cv:
            return len(self.sender.pending)

    def poll(self):
        """The messages received (and :class:`Undelivered` notes) since the
        last call, oldest first."""
        with self._cv:
            out = list(self._inbox)
            self._inbox.clear()
            return out

    def wait(self, timeout):
        """Block up to ``timeout`` s until something is received or acknowledged."""
        with self._cv:
            if not self._inbox:
                self._cv.wait(max(0.0, timeout))

    def receive_progress(self, text):
        """Take in the hub's progress JSON (``topics.PROGRESS_TOPIC``);
        unreadable text is ignored."""
        try:
            doc = json.loads(text)
            arms = doc["arms"]
        except (ValueError, TypeError, KeyError):
            return
        if isinstance(arms, dict):
            with self._cv:
                self._progress = doc
                self._cv.notify_all()

    def progress(self):
        """The hub's latest progress document (dict), or None."""
        with self._cv:
            return getattr(self, "_progress", None)


# ------------------------------------------------------------- job progress

def _label(arm):
    return "%s (R%d)" % (arm.name, arm.id)


def _excerpt(text, limit=160):
    return text if len(text) <= limit else text[:limit] + "..."


class JobTracker:
    """Follows the arms of a job (``programs``: arm name -> ArmProgram) from
    what the link delivers.  :meth:`update` returns the lines to print;
    :attr:`outcome` is None while running, True when every arm is DONE, or
    the failure's reason (str).  :attr:`awaiting_report` is True after an
    ERROR status until the arm's A11 (the reason) arrives."""

    def __init__(self, programs):
        self.programs = {p.arm.id: p for p in programs.values()}
        self.state = {i: None for i in self.programs}
        self.shown = {}              # arm id -> (state, percent // 10) last printed
        self.clocks = {}             # arm id -> clock (M) of its latest report
        self.outcome = None
        self.awaiting_report = False

    @property
    def failed(self):
        return isinstance(self.outcome, str)

    def update(self, msg):
        if isinstance(msg, Undelivered):
            if not self.failed:
                self.outcome = ("the hub never acknowledged %r after %d tries (is the communication hub "
                                "running?)" % (_excerpt(msg.text.partition("\n")[0]), msg.tries))
            return []
        program = self.programs.get(getattr(msg, "robot", None))
        if isinstance(msg, ErrorReport):
            if program is None:
                return ["note: arm R%d (not in this job) reported an error at G-code line %d: %s"
                        % (msg.robot, msg.line, msg.message)]
            if not self.failed or self.awaiting_report:
                self.outcome = self.error_text(program, msg.line, msg.message)
                self.awaiting_report = False
            return []
        if not isinstance(msg, Status) or program is None:
            return []
        if msg.clock is not None:            # reordered delivery: an older report is stale
            if msg.clock < self.clocks.get(msg.robot, -1.0):
                return []
            self.clocks[msg.robot] = msg.clock
        self.state[msg.robot] = msg.state
        key = (msg.state, int(msg.percent // 10))
        lines = []
        if self.shown.get(msg.robot) != key:
            self.shown[msg.robot] = key
            lines.append("  %-14s %-8s layer %d of %d, line %d of %d, %5.1f %%" % (
                _label(program.arm) + ":", msg.state.name, min(msg.layer + 1, program.layers),
                program.layers, msg.line, len(program.lines), msg.percent))
        if msg.state == ArmState.ERROR and not self.failed:
            self.outcome = self.error_text(program, msg.line, "reported state ERROR")
            self.awaiting_report = True
        elif self.outcome is None and all(s == ArmState.DONE for s in self.state.values()):
            self.outcome = True
        return lines

    @staticmethod
    def error_text(program, line, message):
        """"<arm> error at G-code line N: message" and that line of its program."""
        text = "%s error at G-code line %d: %s" % (_label(program.arm), line, message)
        if 1 <= line <= len(program.lines):
            text += "\n    line %d of %s's program: %s" % (line, program.arm.name, program.lines[line - 1])
        return text


def _progress_messages(doc, programs):
    """The hub's progress document as the A10s (and A11s) it summarises,
    for the arms of ``programs`` (id -> ArmProgram) it has heard from."""
    out = []
    for entry in doc.get("arms", {}).values():
        try:
            robot, state = int(entry["id"]), ArmState[entry["state"]]
            status = Status(robot, state, int(entry["layer"] or 0), int(entry["line"] or 0),
                            float(entry["percent"] or 0.0))
        except (KeyError, TypeError, ValueError, AmbotsError):
            continue                      # UNKNOWN (no report yet) or unreadable
        if robot not in programs:
            continue
        error = entry.get("error")
        if state == ArmState.ERROR and isinstance(error, dict):
            try:
                out.append(ErrorReport(robot, int(error.get("line") or 0), str(error.get("message", ""))[:512]))
            except (TypeError, ValueError, AmbotsError):
                pass
        out.append(status)
    return out


# --------------------------------------------------------- programs on disk

_MODE_RE = re.compile(r"^; ambots program for arm .*, mode (\w+)")


def program_file_names(arm):
    """The names a program file of ``arm`` may have: ``<arm name>.gcode``
    (as :func:`ambots.job.write_job` writes them) and ``<robot id>.gcode``
    (as the original named them).  Arm names never start with a digit
    (:func:`ambots.config.load_cell`), so the two never meet."""
    return arm.name + ".gcode", "%d.gcode" % arm.id


def program_files(directory, cell):
    """{arm name: path} of the program file of each arm of ``cell`` found
    in ``directory`` under one of :func:`program_file_names`.  Both names
    for one arm is a :class:`~ambots.errors.GCodeError`: which one to send
    is not guessed."""
    if not os.path.isdir(directory):
        raise GCodeError(directory, 0, "", "no such directory")
    files = {}
    for arm in cell.arms:
        found = [n for n in program_file_names(arm) if os.path.isfile(os.path.join(directory, n))]
        if len(found) > 1:
            raise GCodeError(directory, 0, "", "both %s and %s are there for %s: which to send is not "
                             "guessed; remove one" % (found[0], found[1], _label(arm)))
        if found:
            files[arm.name] = os.path.join(directory, found[0])
    if not files:
        raise GCodeError(directory, 0, "", "no program for any arm of cell %s (looked for %s)" % (
            cell.name, ", ".join(" or ".join(program_file_names(a)) for a in cell.arms)))
    return files


def load_programs(directory, cell):
    """Per-arm programs from ``directory`` (the file of each arm of ``cell``
    found there, see :func:`program_files`): {arm name: ArmProgram}.  An
    arm that another program starts with a ``;@A1`` directive is not
    started by the front end (``start_first`` False).  Raises
    :class:`~ambots.errors.GCodeError` naming the file and line of the
    first problem."""
    from ambots.coordinate import ArmProgram
    from ambots.gcode import is_a_series_line, parse_gcode_text, summarize
    from ambots.program import is_directive, parse_directive

    ids = {a.id for a in cell.arms}
    programs, started = {}, set()
    for arm_name, path in program_files(directory, cell).items():
        arm = cell.arm(arm_name)
        try:
            with open(path, "r", encoding="ascii", newline="") as f:
                text = f.read()
        except UnicodeDecodeError as exc:
            raise GCodeError(path, 0, "", "not ASCII G-code (byte %d)" % exc.start) from None
        lines = text.splitlines()
        mode = "?"
        for n, line in enumerate(lines, 1):
            if n == 1 and _MODE_RE.match(line):
                mode = _MODE_RE.match(line).group(1)
            if is_directive(line):
                msg = parse_directive(line, path, n)
                named = [msg.robot] + ([msg.other] if isinstance(msg, WaitFor) else [])
                unknown = [r for r in named if r not in ids]
                if unknown:
                    raise GCodeError(path, n, line, "directive names R%d, not an arm of cell %s"
                                     % (unknown[0], cell.name))
                if isinstance(msg, WaitFor) and msg.robot != arm.id:
                    raise GCodeError(path, n, line, "a barrier for R%d in the program of %s: "
                                     "written for another cell?" % (msg.robot, _label(arm)))
                if isinstance(msg, Start):
                    started.add(msg.robot)
            elif is_a_series_line(line):
                raise GCodeError(path, n, line, "A-series command in a program file (only ';@' "
                                 "directive lines may carry them)")
        summary = summarize(parse_gcode_text(text, path))      # raises on a bad line
        programs[arm.name] = ArmProgram(arm, mode, lines, layers=summary["layers"])
    for p in programs.values():
        p.start_first = p.arm.id not in started
    return programs


# ------------------------------------------------------------------- the menu

class Menu:
    """The front end's menu (see the module docstring).

    ``link``: see :class:`ReliableLink`.  ``cell``: the loaded cell.
    ``model``: default answer of choice 2 and model of :meth:`print_job`;
    ``out``: output folder (default ``out/<model stem>``); ``slicer``:
    ``builtin``, ``prusa`` or ``auto`` (see the module docstring; the
    command line's default for the menu is ``auto``); ``mode``, ``seam``:
    as ``python -m ambots slice``.  ``input(prompt)``
    reads an answer (EOFError = end of input), ``output(line)`` and
    ``error(line)`` write one (``error`` defaults to ``output``);
    ``clock()`` (s) times the waits.  ``timeout``: how long choice 4 follows
    a print (None: until done or Ctrl-C).
    """

    def __init__(self, link, cell, model=None, out=None, slicer="builtin", mode="concurrent",
                 seam="straight", arms=None, scale=1.0, input=input, output=functools.partial(print, flush=True),
                 error=None, clock=time.monotonic, timeout=None, ack_timeout=DEFAULT_ACK_TIMEOUT_S,
                 poll_period=0.1, error_grace=1.0, typed=None, speed=None, support=True):
        self.link, self.cell = link, cell
        #: support under overhangs (--support on|off; the built-in slicer's, passed to prusa-slicer)
        self.support = support
        #: the clock's pace, simulated s per wall s (None: max, or a real cell): the default timeout
        self.speed = speed
        self.model, self.out = model, out
        self.slicer, self.mode, self.seam = slicer, mode, seam
        self.scale = scale          #: scale factor applied to every model (--scale)
        #: the arms to print with (None: the planner chooses, see ambots.job.run_job)
        self.arms = arms
        self.input, self.say = input, output
        self.complain = error or output
        self.clock, self.timeout = clock, timeout
        self.ack_timeout, self.poll_period, self.error_grace = ack_timeout, poll_period, error_grace
        #: typed() -> the lines typed since the last call, without waiting: the progress
        #: view's controls (p/r/s [arm]); None: no controls (a scripted --print job)
        self.typed = typed
        self.job = None
        self.print_times = {}       # arm name -> estimated print time (s) of the sliced job
        self.programs = {}          # arm name -> ArmProgram: what 3 sends and 4 starts
        self.directory = None       # where the programs are on disk
        self.sent = False           # the hub acknowledged the current programs' A5s
        self._chunk_ids = itertools.count(int(time.time()))
        self._chunk = None          # the chunk id of the programs sent
        self._started = None        # the chunk id this front end has started
        self._backlog = []
        self.actions = {"1": self.demo, "2": self.ask_and_slice, "3": self.send, "4": self.start}

    # --- the loop -------------------------------------------------------------------

    def show(self):
        self.say("")
        self.say("ambots front end - cell %s: %s" % (self.cell.name, ", ".join(_label(a) for a in self.cell.arms)))
        if self.programs:
            self.say("programs: %s%s, %s" % (", ".join(self.programs), " in " + self.directory if self.directory
                                             else "", "sent" if self.sent else "not sent"))
        for key, text in CHOICES:
            self.say("  %s) %s" % (key, text))

    def run(self):
        """The interactive loop; returns the exit status (0)."""
        while True:
            self._notes()
            self.show()
            try:
                answer = self.input("choice [1-5]: ")
            except (EOFError, KeyboardInterrupt):
                self.say("")
                break
            choice = answer.strip()
            if choice == "5":
                break
            action = self.actions.get(choice)
            if action is None:
                what = "no choice given" if not choice else "%r is not a choice" % _excerpt(choice, 40)
                self.complain("%s: answer 1, 2, 3, 4 or 5" % what)
                continue
            self.attempt(action)
        self.say("bye")
        return EXIT_OK

    def attempt(self, action):
        """Run one menu action: a bad input is one line, Ctrl-C returns to
        the menu, and so does end of input at a question (the menu then
        quits).  Anything else unexpected is one line too, so that the
        operator keeps the menu (and can report it)."""
        try:
            return action()
        except (AmbotsError, OSError) as exc:
            self.complain("error: %s" % one_line(exc))
        except KeyboardInterrupt:
            self.say("")
            self.say("interrupted: back to the menu (a print that was started goes on)")
        except EOFError:
            self.say("")
        except Exception as exc:  # noqa: BLE001 -- the menu outlives a bug; one line, not a traceback
            self.complain("internal error (please report it): %s: %s" % (type(exc).__name__, one_line(exc)))
        return False

    def _notes(self):
        """Between actions: show arm errors and undelivered messages, drop old statuses."""
        for msg in self._backlog + self.link.poll():
            if isinstance(msg, ErrorReport):
                self.complain("note: arm R%d reported an error at G-code line %d: %s"
                              % (msg.robot, msg.line, msg.message))
            elif isinstance(msg, Undelivered):
                self.complain("note: the hub never acknowledged %r after %d tries (is the "
                              "communication hub running?)" % (_excerpt(msg.text.partition("\n")[0]),
                                                               msg.tries))
        self._backlog = []

    # --- 1: demo --------------------------------------------------------------------

    def demo(self, deadline=None):
        from ambots.job import DEMO_MODEL
        self.say("demo: %s" % DEMO_MODEL)
        return (self.slice_model(data_path(DEMO_MODEL)) and self.send(deadline)
                and self.start(deadline))

    # --- 2: slice -------------------------------------------------------------------

    def ask(self, question, default=None):
        """One answer (stripped, quotes and ~ removed), ``default`` if empty."""
        answer = self.input("%s [%s]: " % (question, default) if default else "%s: " % question).strip()
        if len(answer) >= 2 and answer[0] == answer[-1] and answer[0] in "'\"":
            answer = answer[1:-1]
        return os.path.expanduser(answer) if answer else default

    def ask_and_slice(self):
        path = self.ask("model file (STL, OBJ, PLY, 3MF; mm)", self.model)
        if not path:
            self.complain("no file given: back to the menu")
            return False
        from ambots.job import DoesNotFit
        try:
            return self.slice_model(path)
        except DoesNotFit as exc:
            self.complain("error: %s" % one_line(exc))
            fit = exc.scale_to_fit
        if fit <= 0:
            return False
        answer = self.ask("scale factor to print it at (at most %g here; Enter: back to the menu)" % fit)
        if not answer:
            return False
        try:
            scale = float(answer)
        except ValueError:
            self.complain("%r is not a number: back to the menu" % _excerpt(answer, 40))
            return False
        return self.slice_model(path, scale=scale)

    def slice_model(self, path, scale=None):
        """Run the job pipeline on ``path`` (scaled by ``scale``, default
        :attr:`scale`) and write the programs; the job becomes the current
        one.  Raises AmbotsError / OSError."""
        scale = self.scale if scale is None else scale
        from ambots.job import run_job, write_job
        from ambots.slicer import choose_backend
        slicer = choose_backend(self.slicer)
        self.say("slicer: %s; %s" % (slicer.description, slicer.reason))
        self.say("slicing %s%s (cell %s, %s slicer, %s mode) ..." % (
            path, "" if scale == 1.0 else " at scale %g" % scale, self.cell.name, slicer.backend, self.mode))
        t0 = time.monotonic()
        from ambots.slicer import SliceSettings
        job = run_job(path, self.cell, self.arms, slicer=slicer.backend, mode=self.mode, seam=self.seam,
                      settings=SliceSettings(support=self.support),
                      scale=scale)
        out = self.out or os.path.join("out", os.path.splitext(os.path.basename(path))[0] or "model")
        summary = write_job(job, out)
        self.job, self.programs, self.directory, self.sent = job, dict(job.programs), out, False
        # each arm's time by the one timing law (its feeds' time if the plan could not be timed)
        self.print_times = {name: a.get("done_s") or a["print_time_s"] for name, a in summary["arms"].items()}
        estimate = (summary.get("plan") or {}).get("makespan_estimate_s")
        if estimate:                 # the one timing law's makespan: longer than the feeds' times
            self.print_times["makespan"] = estimate
        self.say("sliced in %.1f s: model %.0f mm3 -> %s" % (time.monotonic() - t0, summary["model_volume_mm3"],
                                                              ", ".join(self.programs)))
        from ambots.job import arm_time_columns
        self.say("  %-8s %4s %10s %7s %7s %11s %8s %8s %s" % ("arm", "id", "part mm3", "layers", "lines",
                                                               "filament mm", "busy s", "done s", "starts"))
        for name, a in summary["arms"].items():
            p = self.programs[name]
            self.say("  %-8s R%-3d %10.0f %7d %7d %11.1f %s %s" % (
                name, a["id"], a["part_volume_mm3"], a["layers"], len(p.lines), a["extruded_filament_mm"],
                arm_time_columns(a), "by A1" if p.start_first else "after another arm"))
        from ambots.job import overhang_lines, plan_lines, unsupported_line
        from ambots.repair import repair_lines
        for line in repair_lines(summary.get("repair")):
            self.say("  " + line)
        for line in plan_lines(summary.get("plan")):
            self.say("  " + line)
        if summary.get("overhang"):
            self.say("  " + unsupported_line(summary["overhang"]))
            for line in overhang_lines(summary["overhang"]):
                self.say("  " + line)
        self.say("wrote %s" % ", ".join(os.path.join(out, n) for n in
                                       [a + ".gcode" for a in self.programs] + ["job.json"]))
        return True

    # --- 3: send --------------------------------------------------------------------

    def send(self, deadline=None):
        """Send every program as one A5 chunk; True once the hub acknowledged them all."""
        if not self.programs:
            directory = self.ask("directory with the programs (<arm>.gcode or <robot id>.gcode)", self.directory)
            if not directory:
                self.complain("no directory given: slice a model first (2)")
                return False
            files = program_files(directory, self.cell)
            self.programs, self.directory, self.sent = load_programs(directory, self.cell), directory, False
            self.say("loaded %s from %s" % (", ".join(
                n + ".gcode" if os.path.basename(files[n]) == n + ".gcode"
                else "%s for %s" % (os.path.basename(files[n]), _label(p.arm))
                for n, p in self.programs.items()), directory))
        chunk = next(self._chunk_ids) % (MAX_U32 + 1)
        messages = [LoadChunk(p.arm.id, p.text, chunk_id=chunk) for p in self.programs.values()]
        self._chunk = chunk
        self._record_start([])          # programs being sent: no start of them yet
        for p, msg in zip(self.programs.values(), messages):      # all checked before any is sent
            self.link.send(msg)
            self.say("  %-14s A5 chunk C%d: %d lines, %d bytes" % (_label(p.arm) + ":", chunk, len(p.lines),
                                                                 len(msg.gcode)))
        self._drop_statuses()
        self.sent = self.wait_for_hub("the G-code", deadline)
        if self.sent:
            self.say("the hub acknowledged the G-code of %s" % ", ".join(self.programs))
        return self.sent

    def _record_start(self, arms):
        """Write :data:`START_RECORD` in the programs' directory: the chunk id
        sent and the arms given its A1 (``arms``), for a front end that
        replaces this one (:meth:`attach`).  A directory that cannot be
        written is said, and the job goes on without the record."""
        if not self.directory:
            return
        path = os.path.join(self.directory, START_RECORD)
        try:
            tmp = path + ".tmp"
            with open(tmp, "w") as f:
                json.dump({"chunk": self._chunk, "started": arms,
                           "arms": {p.arm.name: p.arm.id for p in self.programs.values()}}, f)
            os.replace(tmp, path)
        except OSError as exc:
            self.complain("warning: could not record the start in %s (%s): a front end that replaces "
                          "this one (--follow) cannot re-send it" % (path, exc.strerror or exc))

    def wait_for_hub(self, what, deadline=None):
        """Wait until the hub has acknowledged everything sent (keeping what
        arrives meanwhile for :meth:`follow`); False and a line if it has not
        by ``deadline`` (default: ``ack_timeout`` from now) or gave up."""
        t0 = self.clock()
        end = t0 + self.ack_timeout if deadline is None else deadline
        while self.link.pending():
            for msg in self.link.poll():
                if isinstance(msg, Undelivered):
                    self.complain("error: the hub never acknowledged %r after %d tries (is the "
                                  "communication hub running?)" % (_excerpt(msg.text.partition("\n")[0]),
                                                                   msg.tries))
                    return False
                self._backlog.append(msg)
            now = self.clock()
            if now >= end:
                self.complain("error: the hub has not acknowledged %s after %.0f s (is the communication "
                              "hub running?); still trying in the background" % (what, now - t0))
                return False
            self.link.wait(min(self.poll_period, end - now))
        return True

    def _drop_statuses(self):
        """Forget statuses received so far: they are about an earlier job."""
        self._backlog = [m for m in self._backlog + self.link.poll() if not isinstance(m, Status)]

    # --- 4: start -------------------------------------------------------------------

    def start(self, deadline=None):
        """A1 to the arms that start first, then :meth:`follow`; True if every arm got DONE."""
        if not self.programs:
            self.complain("nothing to start: slice a model (2) or send G-code (3) first")
            return False
        if not self.sent:
            self.say("the G-code has not been sent yet: sending it first")
            if not self.send(deadline):
                return False
        self._drop_statuses()
        first = [p for p in self.programs.values() if p.start_first]
        # the first start of these programs names their chunk (an arm starts a chunk once, so a
        # replacement front end may send it again); a later one, as in the original, runs a DONE
        # arm again from the top
        chunk = self._chunk if self._started != self._chunk else None
        self._record_start([p.arm.name for p in first])
        for p in first:
            self.link.send(Start(p.arm.id, chunk_id=chunk))
        self._started = self._chunk
        rest = [p for p in self.programs.values() if not p.start_first]
        self.say("A1 sent to %s%s" % (", ".join(_label(p.arm) for p in first),
                                      "; %s start when the arm before them is done" % ", ".join(
                                          _label(p.arm) for p in rest) if rest else ""))
        if not self.wait_for_hub("the start command", deadline):
            return False
        return self.follow(deadline)

    def follow(self, deadline=None, attach=False):
        """Print the arms' progress until every arm of the job is DONE (True)
        or one fails or ``deadline`` (default: :attr:`timeout` from now, or
        never) passes (False, the reason on the error stream).  ``attach``:
        the job was started by another front end (this one may be its
        replacement after a crash), so the hub's progress document counts
        too: it knows the arms' states from before this front end was up."""
        t0 = self.clock()
        if deadline is None and self.timeout is not None:
            deadline = t0 + self.timeout
        self.say("following the print%s (Ctrl-C: back to the menu, the arms go on)" % (
            "" if deadline is None else ", at most %.0f s" % (deadline - t0)))
        if self.typed is not None:
            self.say("  type p, s or r and Enter to pause (end of line), stop (brake now) or resume every arm;"
                     " add an arm's name or id for one arm")
        tracker = JobTracker(self.programs)
        grace_end = None
        seen_progress = None
        while True:
            incoming, self._backlog = self._backlog + self.link.poll(), []
            doc = self.link.progress() if attach and hasattr(self.link, "progress") else None
            if doc is not None and doc is not seen_progress:
                seen_progress = doc
                # only for arms not heard from directly: the document lags their own reports
                incoming = [m for m in _progress_messages(doc, tracker.programs)
                            if m.robot not in tracker.clocks] + incoming
            for msg in incoming:
                for line in tracker.update(msg):
                    self.say(line)
            if self.typed is not None:
                for line in self.typed():
                    self.control(line)
            now = self.clock()
            if tracker.outcome is True:
                self.say("print finished: every arm is DONE (%s) after %.1f s" % (
                    ", ".join(_label(p.arm) for p in self.programs.values()), now - t0))
                return True
            if tracker.failed:
                if tracker.awaiting_report and grace_end is None:
                    grace_end = now + self.error_grace      # the A11 saying why may follow the status
                if not tracker.awaiting_report or now >= grace_end:
                    self.complain("print failed: %s" % tracker.outcome)
                    return False
            if deadline is not None and now >= deadline:
                waiting = ["%s %s" % (_label(tracker.programs[i].arm), s.name if s is not None else "silent")
                           for i, s in tracker.state.items() if s != ArmState.DONE]
                self.complain("print failed: timed out after %.0f s waiting for %s"
                              % (now - t0, ", ".join(waiting)))
                return False
            ends = [t - now for t in (deadline, grace_end) if t is not None]
            self.link.wait(min([self.poll_period] + ends))

    def control(self, line):
        """A line typed in the progress view: pause, stop or resume (see
        :mod:`ambots.control`), sent through the hub like every command."""
        from ambots.control import ControlError, parse_key_line
        try:
            parsed = parse_key_line(self.cell, line)
        except ControlError as exc:
            self.complain("  %s" % exc)
            return
        if parsed is None:
            return
        action, msgs = parsed
        for m in msgs:
            self.link.send(m)
        self.say("  %s sent to %s" % (action, ", ".join(_label(self.cell.arm_by_id(m.robot)) for m in msgs)))

    # --- --follow -------------------------------------------------------------------

    def attach(self, directory, timeout=None):
        """Follow a job that is already running (started by another front
        end, e.g. one that crashed), its programs in ``directory``.  It sends
        only the start recorded there (:meth:`_restart`), which an arm that
        has started ignores, so the print is not disturbed.  The exit status
        as :meth:`print_job`."""
        try:
            self.programs, self.directory = load_programs(directory, self.cell), directory
        except (AmbotsError, OSError) as exc:
            self.complain("error: %s" % one_line(exc))
            return EXIT_BAD_INPUT
        self.sent = True
        self.say("attached to the job of %s in %s" % (", ".join(self.programs), directory))
        deadline = None if timeout is None else self.clock() + timeout
        self._restart(directory)
        return EXIT_OK if self.follow(deadline, attach=True) else EXIT_FAILED

    def _restart(self, directory):
        """Send again the start that the front end this one replaces
        recorded (:meth:`_record_start`), naming its chunk: an arm that has
        started that chunk ignores it, and one whose start was lost with
        that front end (and a hub that had not acknowledged it) starts now."""
        path = os.path.join(directory, START_RECORD)
        try:
            with open(path) as f:
                record = json.load(f)
            chunk, started = int(record["chunk"]), [str(a) for a in record["started"]]
        except FileNotFoundError:
            return
        except (OSError, ValueError, KeyError, TypeError) as exc:
            self.complain("warning: %s is unreadable (%s): the start is not sent again" % (path, one_line(exc)))
            return
        arms = [self.programs[a].arm for a in started if a in self.programs]
        if not arms:
            return
        for arm in arms:
            self.link.send(Start(arm.id, chunk_id=chunk))
        self.sent, self._chunk, self._started = True, chunk, chunk
        self.say("A1 C%d sent again to %s (the start recorded in %s; an arm that has started chunk C%d "
                 "ignores it)" % (chunk, ", ".join(_label(a) for a in arms), START_RECORD, chunk))

    # --- --print --------------------------------------------------------------------

    def print_job(self, model=None, timeout=None):
        """Slice ``model`` (default: ``self.model``, else the demo model),
        send, start and follow; the exit status (0 done, 1 failed, 2 bad input).
        ``timeout`` (s) covers sending, starting and printing; default
        :func:`print_timeout_s` of the longest estimated print time."""
        from ambots.job import DEMO_MODEL
        try:
            self.slice_model(model or self.model or data_path(DEMO_MODEL))
        except (AmbotsError, OSError) as exc:
            self.complain("error: %s" % one_line(exc))
            return EXIT_BAD_INPUT
        if timeout is None:
            timeout = print_timeout_s(max(self.print_times.values(), default=0.0), self.speed)
        deadline = self.clock() + timeout
        try:
            ok = self.send(deadline) and self.start(deadline)
        except (AmbotsError, OSError) as exc:
            self.complain("error: %s" % one_line(exc))
            return EXIT_FAILED
        return EXIT_OK if ok else EXIT_FAILED


# -------------------------------------------------------------------- the command line

def _timeout(text):
    """--timeout: wall s > 0, or "auto" (the default)."""
    if text.strip().lower() in ("", "auto"):
        return None
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value > 0:
        raise argparse.ArgumentTypeError("must be a number of seconds > 0 or auto, not %r" % text)
    return value


def build_parser(prog="front_end"):
    p = argparse.ArgumentParser(
        prog=prog, description="The ambots front end: the menu (1 start demo, 2 slice an STL file, 3 send "
                               "G-code to the arms, 4 start printing, 5 quit), or with --print one whole "
                               "job: slice, send, start, wait; exit 0 when every arm is done, 1 on an arm's "
                               "error or the timeout, 2 on a bad model or cell.")
    p.add_argument("--model", help="model file, mm: choice 2's default answer, and what --print prints "
                                   "(default for --print: the demo block)")
    p.add_argument("--cell", help="cell YAML (default: config/cells/kinova_ur10.yaml)")
    p.add_argument("--slicer", choices=("auto", "builtin", "prusa"),
                   help="auto: PrusaSlicer where prusa-slicer is installed (as the original), else the built-in "
                        "slicer; builtin or prusa: that one, or an error (default: auto in the menu, builtin "
                        "with --print)")
    p.add_argument("--mode", choices=("concurrent", "sequential"), default="concurrent")
    p.add_argument("--seam", choices=("straight", "interlock", "overlap"), default="straight",
                   help="where two arms' parts meet: straight (a plane) or interlock (= overlap: the boundary "
                        "alternates across the plane layer by layer)")
    p.add_argument("--support", choices=("on", "off"), default="on",
                   help="support under overhangs steeper than 45 deg (default on; off: a warning names the layers "
                        "with extrusion in mid-air)")
    p.add_argument("--arms", help="comma-separated arms to print with, e.g. ur10 (default: the planner chooses "
                                  "the fastest of the cell's arms together and each arm alone)")
    p.add_argument("--out", help="output folder of the programs (default: out/<model stem>)")
    p.add_argument("--scale", type=float, default=1.0,
                   help="scale factor applied to the model (default 1; a model too large for the cell is "
                        "refused with the largest factor that fits, and choice 2 asks for one)")
    p.add_argument("--print", dest="print_job", action="store_true",
                   help="run one whole job without the menu and exit with its status")
    p.add_argument("--follow", metavar="DIR",
                   help="attach to a job already running (its programs in DIR, e.g. after the front end "
                        "that started it crashed): send again the start recorded in DIR/%s (an arm that has started "
                        "ignores it), print its progress; exit like --print" % START_RECORD)
    p.add_argument("--timeout", type=_timeout,
                   help="wall s to wait for the print to finish (--print default: %.0f + twice the longest "
                        "estimated print time at the clock's pace, /clock/speed; menu default: no limit)"
                        % DEFAULT_TIMEOUT_BASE_S)
    return p


def menu_from_args(args, link, cell, **kw):
    """A :class:`Menu` configured by :func:`build_parser`'s ``args``."""
    arms = [cell.arm(n.strip()) for n in args.arms.split(",")] if getattr(args, "arms", None) else None
    # the menu slices like the original (PrusaSlicer where installed); a scripted --print job keeps
    # the same G-code on every machine unless --slicer says otherwise
    slicer = args.slicer or ("builtin" if args.print_job else "auto")
    return Menu(link, cell, model=args.model, out=args.out, slicer=slicer, mode=args.mode,
                seam=getattr(args, "seam", "straight"), support=getattr(args, "support", "on") == "on", arms=arms,
                scale=args.scale,
                timeout=None if args.print_job else args.timeout, **kw)
