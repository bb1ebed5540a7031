"""Everything the project starts or imports is installed by ``make setup``.

``make setup`` installs the Debian packages of the Makefile's APT_PACKAGES and
the PyPI distributions of requirements.txt (into the venv); a machine may have
more, users' machines do not.  rosrun once reached users that way: installed
by hand on the CI machine, never by ``make setup``.  These tests fail on any
such use, naming the program or module, the file:line that uses it and what
is missing.

What is scanned (statically: ``ast`` for Python, expat for launch XML, a small
shell tokenizer for the Makefile and shell scripts; nothing is run):

* programs: ``subprocess.*``, ``os.exec*/spawn*/system/popen``,
  ``pexpect.spawn``, ``shutil.which`` ... in Python under src/, nodes/, tests/
  (scripts without .py found by their shebang) whose program is a literal
  (or a name bound once to one); the Makefile's recipes and ``$(shell ...)``
  (make variables expanded by make itself); shell scripts (env.bash, env hooks);
* Python modules: absolute imports anywhere in those files (also inside
  functions), ``__import__``/``importlib.import_module`` of a literal, and
  ``python -m mod`` / ``python -c code`` in argument lists and recipes;
* ROS: ``<node>``/``<test>`` of launch/*.launch and tests/ros/*.test,
  ``$(find pkg)``, ``<param command=...>``, ``launch-prefix``; in Python
  ``roslaunch.core.Node(pkg, type)``, ``roslib.packages.find_node``,
  ``rosrun pkg type`` and ``roslaunch/rostest pkg ...`` argument lists.
  The project's own package (ambots) and files are skipped.

When a use is covered:

* its file (programs: found on PATH with the venv's bin first, as the catkin
  env hook has it at run time; symlinks followed) belongs (``dpkg -S``) to a
  Debian package named in APT_PACKAGES, or to an Essential / Priority:
  required one, or to the interpreter itself (PYTHON_CORE), or to apt (the one
  tool setup needs before it can install anything);
* a module of the standard library is free only if it lives in the core
  python3.11 packages: what Debian splits out (python3-tk, python3-distutils,
  python3.11-venv ...) must be listed;
* a file in the venv belongs to a pip distribution named *directly* in
  requirements.txt (a transitive dependency can vanish with any upgrade), or
  to pip/setuptools, which ``python3 -m venv`` puts in every venv (covered by
  python3-venv in APT_PACKAGES);
* an import that does not resolve at all is allowed only inside a ``try:``
  whose handler catches ImportError/ModuleNotFoundError/Exception (optional).

The venv whose interpreter resolves the modules: ``$AMBOTS_VENV`` if set,
else ROOT/.venv if it exists, else the venv these tests run in (``sys.prefix``
when ``sys.executable`` is a venv interpreter, as with ``make test``).

Reads only the repository and system state (make, dpkg, the interpreters):
one ``make``, one ``dpkg -S``, one ``dpkg-query`` and one venv interpreter
subprocess in all.
"""
import ast
import bisect
import functools
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import xml.parsers.expat
from collections import defaultdict, namedtuple
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
OWN_ROS_PACKAGE = "ambots"
PY_DIRS = ("src", "nodes", "tests")
SKIP_DIRS = {"__pycache__", ".git", ".venv", ".ws", "build", "devel", "out"}

#: the interpreter itself: Debian's core python3.11 (python3-venv and
#: python3-dev depend on it); any other owner of a stdlib module must be listed
PYTHON_CORE = {"libpython3.11-stdlib", "libpython3.11-minimal", "python3.11-minimal", "python3.11"}
#: ... and its programs (/usr/bin/python3 is python3-minimal's)
PYTHON_PROGRAMS = PYTHON_CORE | {"python3", "python3-minimal"}
#: what make setup needs before it can install anything (apt-get; Priority: important)
SETUP_PRECONDITIONS = {"apt"}
#: pip distributions every venv has (`python3 -m venv` bootstraps them): python3-venv's
VENV_BOOTSTRAP = {"pip", "setuptools"}

SYS_EXECUTABLE = "<sys.executable>"     #: the interpreter running the code (skipped as a program)
VENV_TOKEN = "<venv>"                   #: the venv directory, in program paths

#: use of something: kind program|module|code|rosnode|rospkg; category programs|modules|launch
Use = namedtuple("Use", "kind name where category guarded")


#: the test that reports a kind of use (programs: the rest)
_CATEGORY = {"module": "modules", "rosnode": "launch", "rospkg": "launch"}


def _use(kind, name, where, category, guarded=False):
    return Use(kind, name, where, category, guarded)


def _rel(path):
    try:
        return str(Path(path).relative_to(ROOT))
    except ValueError:
        return str(path)


def _norm(name):
    """PEP 503 normalised distribution name."""
    return re.sub(r"[-_.]+", "-", name).lower()


def _walk(top):
    for dirpath, dirnames, filenames in os.walk(top):
        dirnames[:] = sorted(d for d in dirnames if d not in SKIP_DIRS)
        for f in sorted(filenames):
            yield Path(dirpath) / f


def _first_line(path):
    try:
        with open(path, "rb") as f:
            return f.readline(200)
    except OSError:
        return b""


# ----------------------------------------------------------------------------------------------
# shell: a small tokenizer, enough for make recipes and scripts

_BUILTINS = set(
    ". : [ alias bg bind break builtin caller cd command compgen complete compopt continue declare "
    "dirs disown echo enable eval exec exit export false fc fg getopts hash help history jobs kill "
    "let local logout mapfile popd printf pushd pwd read readarray readonly return set shift shopt "
    "source suspend test times trap true type typeset ulimit umask unalias unset wait".split())
#: keywords after which the next word starts a command
_PREFIX_KEYWORDS = {"if", "then", "else", "elif", "do", "while", "until", "!", "{", "}", "time",
                    "fi", "done", "esac"}
_ASSIGNMENT = re.compile(r"[A-Za-z_]\w*(\[[^]]*\])?\+?=")
_OPS = ("&&", "||", ";;&", ";;", ";&", "|&", ";", "|", "&", "(", ")", "\n")
_REDIR = re.compile(r"&>>|&>|>>|>&|<&|<<<|<<-|<<|<>|>\||>|<")
#: wrappers that run their argument as a program, with their options that take a value
_WRAPPERS = {"env": {"-u", "--unset", "-C", "--chdir", "-S", "--split-string"},
             "nice": {"-n", "--adjustment"}, "nohup": set(), "stdbuf": set(),
             "timeout": {"-s", "--signal", "-k", "--kill-after"},
             "sudo": {"-u", "-g", "-C", "-D", "-h", "-p", "-r", "-t", "-U"},
             "xvfb-run": {"-n", "--server-num", "-s", "--server-args", "-e", "--error-file",
                          "-f", "--auth-file", "-p", "--xauth-protocol"}}
_PYTHON = re.compile(r"python[0-9.]*")


def _balanced(text, i):
    """Index of the ``)`` closing the ``(`` at ``i`` (quotes respected)."""
    depth, j, n = 0, i, len(text)
    while j < n:
        c = text[j]
        if c == "\\":
            j += 2
            continue
        if c == "'":
            k = text.find("'", j + 1)
            j = n if k < 0 else k + 1
            continue
        if c == '"':
            j += 1
            while j < n and text[j] != '"':
                j += 2 if text[j] == "\\" else 1
            j += 1
            continue
        if c == "(":
            depth += 1
        elif c == ")":
            depth -= 1
            if depth == 0:
                return j
        j += 1
    return n - 1


def _expansion(text, i, subs, base):
    """End of the expansion ($x, ${x}, $(cmd), $((...)), `cmd`) at ``i``;
    command substitutions go to ``subs`` as (text, offset)."""
    n = len(text)
    if text[i] == "`":
        k = text.find("`", i + 1)
        k = n if k < 0 else k
        subs.append((text[i + 1:k], base + i + 1))
        return k + 1
    nxt = text[i + 1:i + 2]
    if text.startswith("((", i + 1):
        return _balanced(text, i + 1) + 1
    if nxt == "(":
        k = _balanced(text, i + 1)
        subs.append((text[i + 2:k], base + i + 2))
        return k + 1
    if nxt == "{":
        k = text.find("}", i + 2)
        return n if k < 0 else k + 1
    m = re.compile(r"[A-Za-z_]\w*|[0-9@*#?$!-]").match(text, i + 1)
    return m.end() if m else i + 1


def _shell_tokens(text, base=0):
    """([("word", value, dynamic, offset) | ("op"|"redir", op, False, offset)], substitutions)"""
    toks, subs = [], []
    buf, dyn, start = None, False, 0
    i, n = 0, len(text)

    def flush():
        nonlocal buf, dyn
        if buf is not None:
            toks.append(("word", buf, dyn, base + start))
        buf, dyn = None, False

    while i < n:
        c = text[i]
        if buf is None:
            start = i
        if text.startswith("\\\n", i):                      # line continuation
            i += 2
            continue
        if c in " \t":
            flush()
            i += 1
            continue
        if c == "#" and buf is None:                         # comment
            k = text.find("\n", i)
            i = n if k < 0 else k
            continue
        if c in "<>" or (c == "&" and text.startswith("&>", i)):
            if buf is not None and buf.isdigit() and not dyn:  # 2>file: a file descriptor
                buf = None
            flush()
            m = _REDIR.match(text, i)
            toks.append(("redir", m.group(0), False, base + i))
            i = m.end()
            continue
        op = next((o for o in _OPS if text.startswith(o, i)), None)
        if op:
            flush()
            toks.append(("op", op, False, base + i))
            i += len(op)
            continue
        if buf is None:
            buf = ""
        if c == "'":
            k = text.find("'", i + 1)
            k = n if k < 0 else k
            buf += text[i + 1:k]
            i = k + 1
        elif c == '"':
            j = i + 1
            while j < n and text[j] != '"':
                if text[j] == "\\" and j + 1 < n:
                    if text[j + 1] != "\n":
                        buf += text[j + 1] if text[j + 1] in '"\\$`' else text[j:j + 2]
                    j += 2
                elif text[j] in "$`":
                    k = _expansion(text, j, subs, base)
                    buf += text[j:k]
                    dyn = dyn or k > j + 1
                    j = k
                else:
                    buf += text[j]
                    j += 1
            i = j + 1
        elif c in "$`":
            k = _expansion(text, i, subs, base)
            buf += text[i:k]
            dyn = dyn or k > i + 1
            i = k
        elif c == "\\" and i + 1 < n:
            buf += text[i + 1]
            i += 2
        else:
            buf += c
            i += 1
    flush()
    return toks, subs


def _shell_commands(text, base=0):
    """Simple commands of a shell text, command substitutions included: each a
    list of (word, dynamic, offset) starting at the command word."""
    toks, subs = _shell_tokens(text, base)
    cmds, seg, in_case = [], [], False
    for tok in toks + [("op", ";", False, base + len(text))]:
        if tok[0] != "op":
            seg.append(tok)
            continue
        words = [w for w in seg if w[0] == "word"]
        first = words[0][1] if words and not words[0][2] else None
        if first == "case":
            in_case = True                   # `case WORD in`: patterns follow, up to `)`
        elif first == "esac":
            in_case = False
        elif in_case and tok[1] == ")":
            pass                             # a pattern
        else:
            cmd = _command_words(seg)
            if cmd:
                cmds.append(cmd)
        seg = []
    for sub, off in subs:
        cmds += _shell_commands(sub, off)
    return cmds


def _command_words(seg):
    words, skip = [], False
    for kind, val, dyn, off in seg:
        if kind == "redir":
            skip = True                      # its target (file, fd or here-document delimiter)
        elif skip:
            skip = False
        else:
            words.append((val, dyn, off))
    i = 0
    while i < len(words):
        val, dyn, _ = words[i]
        if not dyn and val in ("for", "select", "case", "[[", "function", "in"):
            return []                        # `for x in ...`, `[[ ... ]]`: no program
        if (not dyn and val in _PREFIX_KEYWORDS) or _ASSIGNMENT.match(val) or dyn:
            i += 1                           # keyword, VAR=value, or an unknown `$SUDO`-like prefix
            continue
        break
    words = words[i:]
    if words and words[0][0] in _BUILTINS:
        if words[0][0] in ("exec", "command", "builtin"):
            rest = words[1:]
            if any(w[0] in ("-v", "-V") for w in rest[:2]):
                return []
            while rest and rest[0][0].startswith("-"):
                rest = rest[1:]
            return rest
        return []
    return words


def _shell_programs(text):
    """The program words of a shell text (for the scanner's own test)."""
    out = []
    for cmd in _shell_commands(text):
        out += [name for kind, name, _ in _argv_uses([None if d else v for v, d, _ in cmd])
                if kind == "program"]
    return out


def _argv_uses(argv):
    """What an argument list (str, SYS_EXECUTABLE, or None for what is not a
    literal) starts or loads: [(kind, name, index)]."""
    out, i = [], 0
    while i < len(argv):
        prog = argv[i]
        if not isinstance(prog, str) or not prog:
            break
        if prog != SYS_EXECUTABLE:
            out.append(("program", prog, i))
        base = os.path.basename(prog)
        rest = argv[i + 1:]
        if prog == SYS_EXECUTABLE or _PYTHON.fullmatch(base):
            for j, a in enumerate(rest):
                if a in ("-m", "-c") and j + 1 < len(rest) and isinstance(rest[j + 1], str):
                    if a == "-m":
                        out.append(("module", rest[j + 1].split(".")[0], i + 2 + j))
                    else:
                        out.append(("code", rest[j + 1], i + 2 + j))
                    break
                if not (isinstance(a, str) and a.startswith("-")):
                    break                                    # a script: its file is scanned itself
            break
        if base in _WRAPPERS:
            j = i + 1
            while j < len(argv) and isinstance(argv[j], str) and (
                    argv[j].startswith("-") or (base == "env" and "=" in argv[j])):
                j += 2 if argv[j] in _WRAPPERS[base] else 1
            i = j + (base == "timeout")                       # timeout DURATION COMMAND
            continue
        if base == "rosrun":
            pos = [a for a in rest if not (isinstance(a, str) and a.startswith("-"))][:2]
            if len(pos) == 2 and all(isinstance(a, str) for a in pos):
                out.append(("rosnode", tuple(pos), i))
        elif base in ("roslaunch", "rostest"):
            j = 0
            while j < len(rest) and isinstance(rest[j], str) and rest[j].startswith("-"):
                j += 2 if rest[j] in ("-p", "--port") else 1
            if j + 1 < len(rest) and isinstance(rest[j], str) and "/" not in rest[j] \
                    and ":=" not in rest[j] and not rest[j].endswith((".launch", ".test", ".xml")):
                out.append(("rospkg", rest[j], i))
        break
    return out


# ----------------------------------------------------------------------------------------------
# Python

_CALLS = {"subprocess." + f: "argv" for f in ("run", "Popen", "call", "check_call", "check_output")}
_CALLS.update({"ptyprocess.PtyProcess.spawn": "argv", "pexpect.popen_spawn.PopenSpawn": "argv",
               "os.system": "shell", "os.popen": "shell", "subprocess.getoutput": "shell",
               "subprocess.getstatusoutput": "shell", "asyncio.create_subprocess_shell": "shell",
               "asyncio.create_subprocess_exec": "posargs", "pexpect.spawn": "pexpect",
               "pexpect.spawnu": "pexpect", "pexpect.run": "pexpect", "shutil.which": "prog0",
               "os.posix_spawn": "prog0", "os.posix_spawnp": "prog0",
               "roslaunch.core.Node": "rosnode", "roslaunch.Node": "rosnode",
               "roslib.packages.find_node": "rosnode",
               "roslib.packages.get_pkg_dir": "rospkg",
               "importlib.import_module": "import", "__import__": "import"})
_CALLS.update({"os." + f: "prog0" for f in ("execv", "execve", "execvp", "execvpe", "execl", "execle",
                                              "execlp", "execlpe")})
_CALLS.update({"os." + f: "prog1" for f in ("spawnv", "spawnve", "spawnvp", "spawnvpe", "spawnl",
                                              "spawnle", "spawnlp", "spawnlpe")})
_IMPORT_ERRORS = {"ImportError", "ModuleNotFoundError", "Exception", "BaseException"}


def _catches_import_error(handler):
    if handler.type is None:
        return True
    elts = handler.type.elts if isinstance(handler.type, ast.Tuple) else [handler.type]
    names = {e.id if isinstance(e, ast.Name) else getattr(e, "attr", None) for e in elts}
    return bool(names & _IMPORT_ERRORS)


class _PyFile:
    """One Python source: its imports (with whether they are guarded) and the
    programs, modules and ROS nodes its calls name."""

    def __init__(self, tree, rel):
        self.rel = rel
        self.aliases, self.assigned = {}, defaultdict(list)
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for a in node.names:
                    top = a.name.split(".")[0]
                    self.aliases[a.asname or top] = a.name if a.asname else top
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                for a in node.names:
                    self.aliases[a.asname or a.name] = node.module + "." + a.name
            elif isinstance(node, (ast.Assign, ast.AnnAssign)) and node.value is not None:
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                for t in targets:
                    if isinstance(t, ast.Name):
                        self.assigned[t.id].append(node.value)
        self.uses = []
        self._visit(tree, False)

    def dotted(self, node):
        if isinstance(node, ast.Name):
            return self.aliases.get(node.id, node.id)
        if isinstance(node, ast.Attribute):
            base = self.dotted(node.value)
            return base and base + "." + node.attr
        return None

    def lit(self, node, depth=0):
        """A string the expression surely is (a literal, a name bound once to
        one, sys.executable, os.path.join(os.path.dirname(sys.executable), ...)),
        else None."""
        if node is None or depth > 6:
            return None
        if isinstance(node, ast.Constant):
            return node.value if isinstance(node.value, str) else None
        if self.dotted(node) == "sys.executable":
            return SYS_EXECUTABLE
        if isinstance(node, ast.Name):
            vals = self.assigned.get(node.id, [])
            return self.lit(vals[0], depth + 1) if len(vals) == 1 else None
        if isinstance(node, ast.Call) and not node.keywords:
            f = self.dotted(node.func)
            args = [self.lit(a, depth + 1) for a in node.args]
            if f == "os.path.dirname" and args == [SYS_EXECUTABLE]:
                return VENV_TOKEN + "/bin"
            if f == "os.path.join" and args and all(isinstance(a, str) and a != SYS_EXECUTABLE
                                                    for a in args):
                return os.path.join(*args)
        return None

    def argv(self, node, depth=0):
        if isinstance(node, ast.Name) and len(self.assigned.get(node.id, [])) == 1 and depth < 6:
            return self.argv(self.assigned[node.id][0], depth + 1)
        if isinstance(node, (ast.List, ast.Tuple)):
            return [None if isinstance(e, ast.Starred) else self.lit(e) for e in node.elts]
        return None

    def _add(self, kind, name, line, guarded=False):
        category = _CATEGORY.get(kind, "programs")
        self.uses.append(_use(kind, name, "%s:%d" % (self.rel, line), category, guarded))

    def _add_argv(self, argv, line):
        for kind, name, _ in _argv_uses(argv):
            self._add(kind, name, line)

    def _add_shell(self, text, line):
        for cmd in _shell_commands(text):
            self._add_argv([None if d else v for v, d, _ in cmd], line)

    def _visit(self, node, guarded):
        if isinstance(node, ast.Try) or type(node).__name__ == "TryStar":
            inner = guarded or any(_catches_import_error(h) for h in node.handlers)
            for c in node.body:
                self._visit(c, inner)
            for c in node.handlers + node.orelse + node.finalbody:
                self._visit(c, guarded)
            return
        if isinstance(node, ast.Import):
            for a in node.names:
                self._add("module", a.name.split(".")[0], node.lineno, guarded)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            self._add("module", node.module.split(".")[0], node.lineno, guarded)
        elif isinstance(node, ast.Call):
            self._call(node, guarded)
        for c in ast.iter_child_nodes(node):
            self._visit(c, guarded)

    def _call(self, node, guarded):
        f = self.dotted(node.func)
        # rospkg.RosPack().get_path("pkg")
        if isinstance(node.func, ast.Attribute) and node.func.attr == "get_path" \
                and isinstance(node.func.value, ast.Call) and self.dotted(node.func.value.func) == "rospkg.RosPack":
            f = "roslib.packages.get_pkg_dir"
        how = _CALLS.get(f)
        if how is None:
            return
        args, kw = node.args, {k.arg: k.value for k in node.keywords if k.arg}
        arg = lambda i, *names: args[i] if len(args) > i else next((kw[n] for n in names if n in kw), None)
        line = node.lineno
        if how == "argv":
            first = arg(0, "args", "argv", "cmd")
            text = self.lit(first)
            if isinstance(text, str) and text != SYS_EXECUTABLE:
                self._add_shell(text, line)
            elif self.argv(first):
                self._add_argv(self.argv(first), line)
        elif how == "shell":
            text = self.lit(arg(0, "cmd", "command"))
            if text:
                self._add_shell(text, line)
        elif how == "posargs":
            self._add_argv([self.lit(a) for a in args], line)
        elif how in ("prog0", "prog1"):
            prog = self.lit(arg(0 if how == "prog0" else 1, "cmd", "path", "file"))
            if prog:
                self._add_argv([prog], line)
        elif how == "pexpect":
            cmd, rest = self.lit(arg(0, "command")), self.argv(arg(1, "args"))
            if cmd and cmd != SYS_EXECUTABLE and rest is None:
                try:
                    self._add_argv(shlex.split(cmd), line)
                except ValueError:
                    pass
            elif cmd:
                self._add_argv([cmd] + (rest or []), line)
        elif how == "rosnode":
            pkg, typ = self.lit(arg(0, "package", "pkg")), self.lit(arg(1, "node_type", "type"))
            if pkg and typ:
                self._add("rosnode", (pkg, typ), line)
        elif how == "rospkg":
            pkg = self.lit(arg(0, "package", "name"))
            if pkg:
                self._add("rospkg", pkg, line)
        elif how == "import":
            name = self.lit(arg(0, "name"))
            if name and not name.startswith("."):
                self._add("module", name.split(".")[0], line, guarded)


def _code_imports(code):
    """(module, guarded) of a `python -c` text."""
    try:
        tree = ast.parse(code)
    except SyntaxError:
        return []
    return [(u.name, u.guarded) for u in _PyFile(tree, "-c").uses if u.kind == "module"]


# ----------------------------------------------------------------------------------------------
# Makefile

_MAKE_REF = re.compile(r"\$[({]([A-Za-z_][\w]*)[)}]")


def _make_values(names):
    """Values of the Makefile's variables, as make itself expands them."""
    names = sorted(set(names) | {"APT_PACKAGES", "VENV", "ROOT"})
    rule = "__deps_print: ; @:" + "".join("$(info __deps__ %s=$(%s))" % (n, n) for n in names)
    env = {k: v for k, v in os.environ.items() if k not in ("MAKEFLAGS", "MFLAGS", "MAKELEVEL",
                                                             "MAKEOVERRIDES")}
    r = subprocess.run(["make", "-s", "-C", str(ROOT), "--no-print-directory", "-f", "Makefile",
                        "--eval", rule, "__deps_print"], capture_output=True, text=True, env=env,
                       timeout=60)
    assert r.returncode == 0, "make cannot read the Makefile's variables:\n" + r.stderr
    out = {}
    for line in r.stdout.splitlines():
        if line.startswith("__deps__ "):
            k, _, v = line[len("__deps__ "):].partition("=")
            out[k] = v.strip()
    return out


def _make_expand(s, values):
    """``s`` with make's variables expanded; functions and automatic variables
    ($@, $(if ...)) become an opaque shell expansion."""
    out, i, n = [], 0, len(s)
    while i < n:
        if s[i] != "$":
            out.append(s[i])
            i += 1
            continue
        nxt = s[i + 1:i + 2]
        if nxt == "$":
            out.append("$")
            i += 2
        elif nxt in ("(", "{"):
            j = _balanced(s.replace("{", "(").replace("}", ")"), i + 1)
            inner = s[i + 2:j]
            out.append(values[inner] if inner in values else "${__make__}")
            i = j + 1
        else:
            out.append("${__make__}")
            i += 2
    return "".join(out)


def _makefile_units(text):
    """The shell texts of the Makefile, each as its physical lines [(line
    number, text)]: every recipe line (with its continuation lines) and every
    $(shell ...)."""
    lines = text.split("\n")
    units, in_rule, i = [], False, 0
    while i < len(lines):
        line = lines[i]
        if line.startswith("\t") and in_rule:
            phys = [(i + 1, re.sub(r"^[ @+-]*", "", line[1:]))]
            while phys[-1][1].endswith("\\") and i + 1 < len(lines):
                i += 1
                nxt = lines[i]
                phys.append((i + 1, nxt[1:] if nxt.startswith("\t") else nxt))
            units.append(phys)
        else:
            logical = line
            while logical.endswith("\\") and i + 1 < len(lines):
                i += 1
                logical = logical[:-1] + " " + lines[i]
            s = logical.strip()
            if not s or s.startswith("#"):
                pass
            elif re.match(r"(override\s+|export\s+)?[\w.$(){}-]+\s*(:{1,3}=|\?=|\+=|!=|=)", s):
                in_rule = False
            else:
                in_rule = re.match(r"[^=#;]+:(?!=)", s) is not None
        i += 1
    # $(shell ...) anywhere
    for m in re.finditer(r"\$\(shell\s", text):
        j = _balanced(text, m.start() + 1)
        units.append([(text.count("\n", 0, m.start()) + 1, text[m.end():j])])
    return units


def _scan_makefile(uses):
    rel = "Makefile"
    text = (ROOT / rel).read_text()
    values = _make_values(_MAKE_REF.findall(text))
    venv_prefix = values.get("VENV", "").rstrip("/") + "/"
    n_cmds = 0
    for phys in _makefile_units(text):
        joined, starts = "", []
        for ln, t in phys:
            starts.append((len(joined), ln))
            joined += _make_expand(t, values) + "\n"
        offsets = [o for o, _ in starts]
        line_of = lambda off: starts[max(0, bisect.bisect_right(offsets, off) - 1)][1]
        for cmd in _shell_commands(joined):
            n_cmds += 1
            argv = [None if d else v for v, d, _ in cmd]
            argv = [VENV_TOKEN + "/" + a[len(venv_prefix):] if isinstance(a, str) and
                    a.startswith(venv_prefix) else a for a in argv]
            for kind, name, idx in _argv_uses(argv):
                where = "%s:%d" % (rel, line_of(cmd[idx][2]))
                if kind == "code":
                    for mod, guarded in _code_imports(name):
                        uses.append(_use("module", mod, where, "modules", guarded))
                else:
                    cat = _CATEGORY.get(kind, "programs")
                    uses.append(_use(kind, name, where, cat))
    return values, n_cmds


# ----------------------------------------------------------------------------------------------
# launch and rostest files

_FIND = re.compile(r"\$\(find\s+([^\s)]+)\)")
_FIRST_WORD = re.compile(r"\s*((?:\$\([^)]*\)|[^\s$]|\$(?!\())+)")    # $(find x)/bin counts as one word


def _scan_launch(path, uses):
    rel = _rel(path)
    parser = xml.parsers.expat.ParserCreate()

    def start(tag, attrs):
        where = "%s:%d" % (rel, parser.CurrentLineNumber)
        for value in attrs.values():
            for pkg in _FIND.findall(value):
                uses.append(_use("rospkg", pkg, where, "launch"))
        if tag in ("node", "test") and "pkg" in attrs and "type" in attrs \
                and "$(" not in attrs["pkg"] + attrs["type"]:
            uses.append(_use("rosnode", (attrs["pkg"], attrs["type"]), where, "launch"))
        for attr in ("command", "launch-prefix"):
            m = _FIRST_WORD.match(attrs.get(attr, "")) if tag == "param" or attr == "launch-prefix" else None
            if m and "$(" not in _FIND.sub("", m.group(1)):        # not $(arg ...) and the like
                uses.append(_use("program", m.group(1), where, "launch"))

    parser.StartElementHandler = start
    parser.Parse(path.read_bytes(), True)


# ----------------------------------------------------------------------------------------------
# everything

def _venv_dir():
    """The venv whose interpreter the code runs on (see the module doc)."""
    if os.environ.get("AMBOTS_VENV"):
        return Path(os.environ["AMBOTS_VENV"])
    if (ROOT / ".venv" / "bin" / "python").exists():
        return ROOT / ".venv"
    if sys.prefix != sys.base_prefix:
        return Path(sys.prefix)
    raise AssertionError("no venv: neither $AMBOTS_VENV nor %s/.venv, and %s is not a venv "
                         "interpreter (run `make setup`)" % (ROOT, sys.executable))


def _requirements():
    names = set()
    for line in (ROOT / "requirements.txt").read_text().splitlines():
        line = line.split(" #", 1)[0].strip()
        m = re.match(r"[A-Za-z0-9][A-Za-z0-9._-]*", line)
        if m and not line.startswith("#"):
            names.add(_norm(m.group(0)))
    return names


#: run by the venv's interpreter (-I: no PYTHONPATH, no user site, no cwd)
_VENV_PROBE = r"""
import importlib.metadata as md, importlib.util, json, os, sys, sysconfig
req = json.load(sys.stdin)
paths = sysconfig.get_paths()
sites = sorted({paths["purelib"], paths["platlib"]})
out = {"stdlib": [paths["stdlib"], paths["platstdlib"]], "sites": sites, "executable": sys.executable,
       "stdlib_names": sorted(sys.stdlib_module_names), "specs": {}, "top": {}, "files": {}}
for name in req["modules"]:
    try:
        spec = importlib.util.find_spec(name)
    except Exception as exc:
        spec = None
    out["specs"][name] = None if spec is None else {
        "origin": spec.origin, "locations": list(spec.submodule_search_locations or [])}
dists = list(md.distributions(path=sites))
names = {d.metadata["Name"] for d in dists}
for top, ds in md.packages_distributions().items():
    mine = sorted({d for d in ds if d in names})
    if mine:
        out["top"][top] = mine
wanted = {os.path.normpath(f) for f in req["files"]}
wanted |= {os.path.normpath(s["origin"]) for s in out["specs"].values()    # single-file modules (.so)
           if s and s["origin"] and any(s["origin"].startswith(d + "/") for d in sites)}
for d in dists if wanted else ():
    for f in d.files or ():
        p = os.path.normpath(str(d.locate_file(f)))
        if p in wanted:
            out["files"][p] = d.metadata["Name"]
print(json.dumps(out))
"""

_MERGED_USR = ("bin", "sbin", "lib", "lib32", "lib64", "libx32")


def _dpkg_names(path):
    """``path`` and its merged-/usr alias (dpkg may know /bin/ls, not /usr/bin/ls)."""
    parts = path.split("/")
    if len(parts) > 3 and parts[1] == "usr" and parts[2] in _MERGED_USR:
        return [path, "/" + "/".join(parts[2:])]
    if len(parts) > 2 and parts[1] in _MERGED_USR:
        return [path, "/usr" + path]
    return [path]


def _dpkg_owners(paths):
    """{path: [Debian packages]} of the paths dpkg knows, in one ``dpkg -S``."""
    paths = sorted({q for p in paths for q in _dpkg_names(p) if not re.search(r"[*?\[]", q)})
    if not paths:
        return {}
    r = subprocess.run(["dpkg", "-S"] + paths, capture_output=True, text=True, timeout=60)
    owners = {}
    for line in r.stdout.splitlines():
        if line.startswith("diversion by") or ": " not in line:
            continue
        pkgs, _, path = line.partition(": ")
        owners[path] = [p.strip().split(":")[0] for p in pkgs.split(",")]
    return owners


def _dpkg_required(pkgs):
    """The packages of ``pkgs`` that every Debian system has (Essential or Priority: required)."""
    if not pkgs:
        return set()
    r = subprocess.run(["dpkg-query", "-W", "-f=${Package}\t${Essential}\t${Priority}\n"] + sorted(pkgs),
                       capture_output=True, text=True, timeout=60)
    out = set()
    for line in r.stdout.splitlines():
        name, essential, priority = (line.split("\t") + ["", "", ""])[:3]
        if essential == "yes" or priority == "required":
            out.add(name)
    return out


class Analysis:
    """The scan, the set-up lists and every problem, by category."""

    def __init__(self):
        self.uses, self.python_files, self.launch_files, self.shell_files = [], [], [], []
        self.problems = defaultdict(list)
        self.module_info = {}          #: module -> (classification, detail)
        self.ros_paths = {}            #: ("rosnode", (pkg, type)) | ("rospkg", pkg) -> path
        self._scan()
        self._resolve()

    # -- scan -----------------------------------------------------------------------------------
    def _scan(self):
        # the project's own modules: src/'s top level (ambots) and the test helpers
        # (tests put their own folders on sys.path)
        own = {"ambots"} | {d.stem for d in (ROOT / "src").iterdir()}
        for d in PY_DIRS:
            for p in _walk(ROOT / d):
                if p.suffix == ".py" or (not p.suffix and re.match(rb"#!.*python", _first_line(p))):
                    self.python_files.append(p)
                    if d == "tests":
                        own.add(p.stem if p.name != "__init__.py" else p.parent.name)
        self.own_modules = own
        for p in self.python_files:
            rel = _rel(p)
            try:
                tree = ast.parse(p.read_bytes(), str(p))
            except SyntaxError as exc:
                self.problems["modules"].append("%s:%s does not parse: %s" % (rel, exc.lineno, exc.msg))
                continue
            f = _PyFile(tree, rel)
            for u in f.uses:
                if u.kind == "code":
                    self.uses += [_use("module", m, u.where, "modules", g) for m, g in _code_imports(u.name)]
                else:
                    self.uses.append(u)
        self.make_values, self.make_commands = _scan_makefile(self.uses)
        self.apt = set(self.make_values["APT_PACKAGES"].split())
        # shell scripts: top-level ones (env.bash) and those under config/, tests/
        candidates = [p for p in sorted(ROOT.iterdir()) if p.is_file()]
        candidates += list(_walk(ROOT / "config")) + list(_walk(ROOT / "tests"))
        for p in candidates:
            if re.search(r"\.(sh|bash)(\.in)?$", p.name) or re.match(rb"#!.*\b(ba|da)?sh\b", _first_line(p)):
                self.shell_files.append(p)
                text = p.read_text(errors="replace")
                for cmd in _shell_commands(text):
                    where = "%s:%d" % (_rel(p), text.count("\n", 0, cmd[0][2]) + 1)
                    for kind, name, _ in _argv_uses([None if d else v for v, d, _ in cmd]):
                        if kind == "code":
                            self.uses += [_use("module", m, where, "modules", g) for m, g in _code_imports(name)]
                        else:
                            self.uses.append(_use(kind, name, where, _CATEGORY.get(kind, "programs")))
        self.launch_files = sorted((ROOT / "launch").glob("*.launch")) + \
            sorted((ROOT / "tests" / "ros").glob("*.test"))
        for p in self.launch_files:
            _scan_launch(p, self.uses)
        self.requirements = _requirements()
        self.venv = _venv_dir()

    # -- resolve --------------------------------------------------------------------------------
    def _resolve(self):
        venv = os.path.realpath(str(self.venv))
        in_venv = lambda p: p.startswith(venv + "/")
        # a program's entry (its directory resolved, not the file: the venv's python is a
        # symlink to Debian's interpreter)
        entry = lambda p: os.path.join(os.path.realpath(os.path.dirname(p)), os.path.basename(p))
        path_env = os.pathsep.join([os.path.join(venv, "bin"), os.environ.get("PATH", os.defpath)])
        by_key = defaultdict(list)                 # (kind, name, category) -> [Use]
        for u in self.uses:
            by_key[(u.kind, u.name, u.category)].append(u)

        # ROS nodes and packages (roslib from Debian's python3-roslib, in this process)
        rospack_error = None
        try:
            import roslib.packages
        except ImportError as exc:
            rospack_error = "roslib is not importable by %s (%s)" % (sys.executable, exc)

        def ros_find(pkg):
            return str(ROOT) if pkg == OWN_ROS_PACKAGE else roslib.packages.get_pkg_dir(pkg)

        for (kind, name, cat) in list(by_key):
            if kind not in ("rosnode", "rospkg"):
                continue
            pkg = name[0] if kind == "rosnode" else name
            if pkg == OWN_ROS_PACKAGE or rospack_error:
                continue
            try:
                if kind == "rosnode":
                    found = [p for p in roslib.packages.find_node(pkg, name[1]) if os.access(p, os.X_OK)]
                    self.ros_paths[(kind, name)] = found[0] if found else None
                else:
                    self.ros_paths[(kind, name)] = os.path.join(ros_find(pkg), "package.xml")
            except Exception:                                   # rospkg.ResourceNotFound and kin
                self.ros_paths[(kind, name)] = None

        # programs: where PATH (venv's bin first) finds them
        prog_paths = {}
        for (kind, name, cat) in by_key:
            if kind != "program":
                continue
            prog = name
            for pkg in _FIND.findall(prog):                       # $(find xacro)/xacro
                try:
                    prog = prog.replace("$(find %s)" % pkg, ros_find(pkg))
                except Exception:
                    prog = None
                    break
            if prog is None:
                prog_paths[name] = None
                continue
            if prog.startswith(VENV_TOKEN):
                prog = venv + prog[len(VENV_TOKEN):]
            if "/" in prog:
                absolute = os.path.isabs(prog)
                inside = absolute and not in_venv(entry(prog)) and \
                    os.path.realpath(prog).startswith(str(ROOT) + "/")
                if not absolute or inside:
                    prog_paths[name] = "own"                        # the project's own file
                    continue
                prog_paths[name] = prog if os.path.exists(prog) else None
            else:
                prog_paths[name] = shutil.which(prog, path=path_env)

        # modules and venv files: one subprocess into the venv's interpreter
        modules = sorted({n for (k, n, _) in by_key if k == "module" and n not in self.own_modules})
        venv_files = sorted({os.path.realpath(p) for p in prog_paths.values()
                             if p and p != "own" and in_venv(os.path.realpath(p))})
        py = os.path.join(venv, "bin", "python")
        r = subprocess.run([py, "-I", "-c", _VENV_PROBE], input=json.dumps(
            {"modules": modules, "files": venv_files}), capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, "the venv interpreter %s failed:\n%s" % (py, r.stderr)
        probe = json.loads(r.stdout)
        sites = [s.rstrip("/") + "/" for s in probe["sites"]]
        stdlib_dirs = [s.rstrip("/") + "/" for s in probe["stdlib"]]
        stdlib_names = set(probe["stdlib_names"])

        # module files
        mod_paths = {}
        for name in modules:
            spec = probe["specs"].get(name)
            if spec is None:
                mod_paths[name] = None
            elif spec["origin"] in (None, "built-in", "frozen") and not spec["locations"]:
                mod_paths[name] = "builtin"
            else:
                origin = spec["origin"] if spec["origin"] not in (None, "built-in", "frozen") else None
                mod_paths[name] = [origin] if origin else spec["locations"]

        # one dpkg -S for everything outside the venv
        wanted = []
        for p in prog_paths.values():
            if p and p != "own":
                wanted += [p, os.path.realpath(p)]
        for p in mod_paths.values():
            if isinstance(p, list):
                wanted += p
        wanted += [p for p in self.ros_paths.values() if p]
        wanted += [os.path.realpath(p) for p in self.ros_paths.values() if p]
        owners = _dpkg_owners([w for w in wanted if not in_venv(w)])
        self.owners = owners
        required = _dpkg_required({p for ps in owners.values() for p in ps})

        def debs(*paths):
            out = []
            for p in paths:
                for q in _dpkg_names(p):
                    out += [d for d in owners.get(q, []) if d not in out]
            return out

        def covered(pkgs, extra=()):
            return any(p in self.apt or p in required or p in SETUP_PRECONDITIONS or p in extra
                       for p in pkgs)

        def wheres(us):
            return ", ".join(sorted({u.where for u in us}, key=_where_key))

        def venv_dist_problem(what, dists, used, verb="used"):
            if any(_norm(d) in self.requirements for d in dists):
                return None
            if any(_norm(d) in VENV_BOOTSTRAP for d in dists) and "python3-venv" in self.apt:
                return None
            if not dists:
                return "%s (in the venv, %s at %s) belongs to no pip distribution: make setup " \
                       "must install it" % (what, verb, used)
            return "%s (pip distribution %s in the venv, %s at %s) is not named in requirements.txt " \
                   "(a transitive pip dependency is not enough: the code uses it, so it must be pinned)" \
                   % (what, "/".join(sorted(set(dists))), verb, used)

        for (kind, name, cat), us in sorted(by_key.items(), key=lambda kv: (kv[0][0], str(kv[0][1]))):
            used = wheres(us)
            if kind == "program":
                path = prog_paths.get(name)
                if path == "own":
                    continue
                if path is None:
                    self.problems[cat].append("%s (used at %s) is not installed on this machine: make setup "
                                              "must install the package that provides it" % (name, used))
                    continue
                real = os.path.realpath(path)
                if in_venv(entry(path)) and in_venv(real):
                    dist = probe["files"].get(os.path.normpath(real))
                    msg = venv_dist_problem(name, [dist] if dist else [], used)
                    if msg:
                        self.problems[cat].append(msg)
                    continue
                pkgs = debs(path, real)
                if not pkgs:
                    self.problems[cat].append("%s (%s, used at %s) belongs to no Debian package and is not in "
                                              "the venv (installed by hand?): make setup must install the "
                                              "package that provides it" % (name, real, used))
                elif not covered(pkgs, PYTHON_PROGRAMS):
                    self.problems[cat].append("%s (Debian package %s, used at %s) is not in the Makefile's "
                                              "APT_PACKAGES" % (name, "/".join(pkgs), used))
            elif kind == "module":
                if name in self.own_modules:
                    continue
                path = mod_paths.get(name)
                if path is None:
                    unguarded = [u for u in us if not u.guarded]
                    self.module_info[name] = ("missing", None)
                    if unguarded:
                        self.problems[cat].append(
                            "module %s (imported at %s) is not importable by the venv interpreter %s: make "
                            "setup must install the package that provides it (APT_PACKAGES or "
                            "requirements.txt)" % (name, wheres(unguarded), py))
                    continue
                if path == "builtin":
                    self.module_info[name] = ("builtin", None)
                    if name not in stdlib_names:
                        self.problems[cat].append("module %s (imported at %s) is built into %s but not part "
                                                  "of the standard library" % (name, used, py))
                    continue
                first = path[0]
                if not in_venv(first) and os.path.realpath(first).startswith(str(ROOT) + "/"):
                    continue                                   # the project's own (a helper on sys.path)
                if any(first.startswith(s) for s in sites):
                    dists = probe["top"].get(name) or [probe["files"][f] for f in map(os.path.normpath, path)
                                                        if f in probe["files"]]
                    self.module_info[name] = ("venv", dists)
                    msg = venv_dist_problem("module " + name, dists, used, "imported")
                    if msg:
                        self.problems[cat].append(msg)
                    continue
                pkgs = debs(*path)
                is_stdlib = name in stdlib_names and any(first.startswith(s) for s in stdlib_dirs) \
                    and "-packages/" not in first
                self.module_info[name] = ("stdlib" if is_stdlib else "debian", pkgs)
                if not pkgs:
                    self.problems[cat].append("module %s (%s, imported at %s) belongs to no Debian package and "
                                              "to no pip distribution in the venv (installed by hand?): make "
                                              "setup must install it" % (name, first, used))
                elif is_stdlib and not covered(pkgs, PYTHON_CORE):
                    self.problems[cat].append("module %s (standard library, which Debian ships separately in "
                                              "%s, imported at %s) is not in the Makefile's APT_PACKAGES"
                                              % (name, "/".join(pkgs), used))
                elif not is_stdlib and not covered(pkgs):
                    self.problems[cat].append("module %s (Debian package %s, imported at %s) is not in the "
                                              "Makefile's APT_PACKAGES" % (name, "/".join(pkgs), used))
            elif kind in ("rosnode", "rospkg"):
                pkg = name[0] if kind == "rosnode" else name
                if pkg == OWN_ROS_PACKAGE:
                    continue
                what = "ROS node %s/%s" % name if kind == "rosnode" else "ROS package %s" % name
                if rospack_error:
                    self.problems[cat].append("%s (used at %s) cannot be resolved: %s" % (what, used,
                                                                                          rospack_error))
                    continue
                path = self.ros_paths.get((kind, name))
                if path is None:
                    self.problems[cat].append("%s (used at %s) is not installed on this machine: make setup "
                                              "must install the package that provides it" % (what, used))
                    continue
                pkgs = debs(path, os.path.realpath(path))
                if not pkgs:
                    self.problems[cat].append("%s (%s, used at %s) belongs to no Debian package (installed by "
                                              "hand?): make setup must install it" % (what, path, used))
                elif not covered(pkgs):
                    self.problems[cat].append("%s (%s, Debian package %s, used at %s) is not in the Makefile's "
                                              "APT_PACKAGES" % (what, path, "/".join(pkgs), used))


def _where_key(where):
    f, _, line = where.rpartition(":")
    return (f, int(line) if line.isdigit() else 0)


@functools.lru_cache(maxsize=None)
def analysis():
    return Analysis()


def _report(category, title):
    problems = analysis().problems[category]
    assert not problems, "%d %s not installed by `make setup`:\n  - %s" % (
        len(problems), title, "\n  - ".join(problems))


# ----------------------------------------------------------------------------------------------
# the tests

def test_programs_the_code_and_the_makefile_start_are_installed_by_setup():
    _report("programs", "program(s) started by the code, the Makefile or the shell scripts")


def test_python_modules_the_code_imports_are_installed_by_setup():
    _report("modules", "imported module(s)")


def test_ros_nodes_and_packages_of_the_launch_files_are_installed_by_setup():
    _report("launch", "ROS node(s)/package(s)/program(s) of the launch and rostest files "
                      "(and of the roslaunch/roslib API)")


def test_the_scanner_finds_what_it_must():
    """So that the tests above cannot pass by scanning nothing."""
    a = analysis()
    assert len(a.python_files) >= 30, a.python_files
    assert any(p.name == "capture" for p in a.python_files), "nodes/ without .py are found by their shebang"
    assert len(a.launch_files) >= 4, a.launch_files
    assert a.make_commands >= 20 and "python3-rospy" in a.apt and a.requirements, (a.make_commands, a.apt)
    uses = {(u.kind, u.name): u for u in a.uses}
    assert ("program", "Xvfb") in uses and uses[("program", "Xvfb")].where.startswith(
        "src/ambots/ros/capture.py:"), "Xvfb of capture.py"
    rsp = [u for u in a.uses if u.kind == "rosnode" and u.name == ("robot_state_publisher",) * 2]
    assert rsp and all(u.category == "launch" for u in rsp), "robot_state_publisher (cell.py's roslaunch Node)"
    assert a.ros_paths[("rosnode", ("robot_state_publisher",) * 2)], "robot_state_publisher resolves"
    assert ("program", "catkin_make") in uses and uses[("program", "catkin_make")].where.startswith("Makefile:")
    assert ("module", "rospy") in uses and ("module", "PIL") in uses and ("module", "numpy") in uses
    assert a.module_info["rospy"] == ("debian", ["python3-rospy"]), a.module_info["rospy"]
    assert a.module_info["json"][0] == "stdlib", a.module_info["json"]
    assert a.module_info["trimesh"] == ("venv", ["trimesh"]), a.module_info["trimesh"]
    assert "ambots" not in a.module_info
    # the shell and argv parsers
    assert _shell_programs(
        'source x && cd y && FOO=1 $SUDO apt-get -q 2>/dev/null | grep -q "a b" || '
        '{ tail -40 log; exit 1; }; for p in a b; do dpkg-query -W $p; done; X=$(id -u) # md5sum\n'
        'case "$X" in 0) cut -c1 ;; *) ;; esac') == ["apt-get", "grep", "tail", "dpkg-query", "cut", "id"]
    assert _argv_uses(["env", "A=1", "timeout", "5", "rosrun", "rviz", "rviz", "-d", None]) == [
        ("program", "env", 0), ("program", "timeout", 2), ("program", "rosrun", 4),
        ("rosnode", ("rviz", "rviz"), 4)]
    assert _argv_uses([SYS_EXECUTABLE, "-m", "pytest.main", "-q"]) == [("module", "pytest", 2)]
