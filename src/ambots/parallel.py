"""Independent work of the front end run side by side in forked processes.

The planner times several plans of one job (each arm alone, the arms
together) and each plan's arms one by one; these are independent and
CPU-bound Python, so threads would not help.  A forked child starts with
the parent's memory (the mesh, the cell, the sliced model: nothing to send)
and sends back only its result, pickled through a temporary file.

``AMBOTS_JOBS`` sets how many processes may work at once (default: the CPUs
this process may run on); ``AMBOTS_JOBS=1`` runs everything in the calling
process, in order.  A child's exception is raised again in the parent (when
it cannot be pickled: a :class:`WorkerError` with its type and message); a
child that dies (a signal, ``os._exit``) raises :class:`WorkerError`.
Children end with ``os._exit``: no ``atexit`` handler, no ROS shutdown hook
and no destructor of the parent's objects runs twice.  A worker starts no
workers of its own.
"""
import os
import pickle
import sys
import tempfile

#: the environment variable that sets the number of processes (1: no fork)
JOBS_ENV = "AMBOTS_JOBS"


class WorkerError(RuntimeError):
    """A forked worker died, or its error or result could not be sent back."""


#: True in a forked worker: it does its work itself (no workers of its own,
#: so that nested calls do not start more processes than there are CPUs)
_IN_WORKER = False


def workers():
    """How many processes may work at once: ``AMBOTS_JOBS`` if set (at least
    1), else the number of CPUs this process may run on; 1 in a worker."""
    if _IN_WORKER:
        return 1
    value = os.environ.get(JOBS_ENV, "").strip()
    if value:
        try:
            return max(1, int(value))
        except ValueError:
            raise WorkerError("%s=%r: expected a whole number of processes" % (JOBS_ENV, value)) from None
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _portable(exc):
    """``exc`` if it survives pickling, else a :class:`WorkerError` naming it."""
    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:
        return WorkerError("%s: %s" % (type(exc).__name__, exc))


def _flush():
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:
            pass


def _child(fn, fd):
    """In the child: run ``fn``, write (ok, value) to ``fd``, exit."""
    global _IN_WORKER
    _IN_WORKER = True
    del _LIVE[:]                              # the parent's children are not this one's
    code = 0
    try:
        try:
            payload = (True, fn())
        except BaseException as exc:          # noqa: B902 -- everything goes back to the parent
            payload = (False, _portable(exc))
        try:
            data = pickle.dumps(payload, protocol=pickle.HIGHEST_PROTOCOL)
        except Exception as exc:
            data = pickle.dumps((False, WorkerError("the result could not be sent back: %s" % exc)))
        with os.fdopen(fd, "wb") as f:
            f.write(data)
    except BaseException:                     # noqa: B902
        code = 1
    finally:
        _flush()
        os._exit(code)


#: the :class:`Forked` children started by this process and not yet
#: collected: :func:`fork_map` counts those still working against
#: :func:`workers`
_LIVE = []


def _working():
    """How many of this process's :class:`Forked` children still work."""
    _LIVE[:] = [f for f in _LIVE if not f.done()]
    return len(_LIVE)


class Forked:
    """``fn()`` started in a forked process (when :func:`workers` > 1);
    :meth:`result` waits for it and returns its value or raises its error.
    With one worker, ``fn`` runs in :meth:`result`, in this process."""

    def __init__(self, fn, fork=None, track=True):
        self._fn, self.pid, self._path = fn, None, None
        if not (workers() > 1 if fork is None else fork) or not hasattr(os, "fork"):
            return
        fd, self._path = tempfile.mkstemp(prefix="ambots-worker-", suffix=".pickle")
        _flush()                             # the child must not print the parent's buffered output again
        try:
            pid = os.fork()
        except OSError:                      # no process left: run here
            os.close(fd)
            os.unlink(self._path)
            self._path = None
            return
        if pid == 0:
            _child(fn, fd)                   # never returns
        os.close(fd)
        self.pid = pid
        if track:
            _LIVE.append(self)

    def done(self):
        """True when :meth:`result` will not wait."""
        if self.pid in (None, -1):
            return True
        pid, status = os.waitpid(self.pid, os.WNOHANG)
        if pid == 0:
            return False
        self._status, self.pid = status, -1
        return True

    def result(self):
        if self.pid is None:
            return self._fn()
        if self.pid != -1:
            _, self._status = os.waitpid(self.pid, 0)
            self.pid = -1
        try:
            with open(self._path, "rb") as f:
                data = f.read()
        finally:
            os.unlink(self._path)
        if not data:
            raise WorkerError("a worker process died (%s)" % _how(self._status))
        ok, value = pickle.loads(data)
        if ok:
            return value
        raise value

    def cancel(self):
        """Stop the child if it still runs (its result is lost)."""
        if self.pid not in (None, -1):
            try:
                os.kill(self.pid, 9)
                os.waitpid(self.pid, 0)
            except OSError:
                pass
            self.pid = -1
        if self._path and os.path.exists(self._path):
            os.unlink(self._path)


def _how(status):
    if os.WIFSIGNALED(status):
        return "signal %d" % os.WTERMSIG(status)
    return "exit code %d" % os.WEXITSTATUS(status)


def fork_map(fn, items, share=True):
    """``[fn(x) for x in items]``, the items shared among :func:`workers`
    processes: this one and forked children (at most workers - 1 at once,
    less those of this process's :class:`Forked` children still working,
    unless ``share`` is False).
    The first error, in item order, is raised once every child has ended."""
    items = list(items)
    n = workers()
    if n > 1 and share:
        n -= _working()
    if n < 2 or len(items) < 2:
        return [fn(x) for x in items]
    results, running = [None] * len(items), {}     # running: item index -> Forked
    done = {}                                      # item index -> (ok, value)
    try:
        i = 0
        while i < len(items):
            # children for the next items, keeping the last one for this process
            while len(running) < n - 1 and i < len(items) - 1:
                running[i] = Forked(lambda x=items[i]: fn(x), fork=True, track=False)
                i += 1
            try:
                done[i] = (True, fn(items[i]))
            except Exception as exc:              # noqa: B902 -- raised in item order below
                done[i] = (False, exc)
            i += 1
            for j in [j for j, f in running.items() if f.done()]:
                done[j] = _collect(running.pop(j))
        for j in sorted(running):
            done[j] = _collect(running.pop(j))
    finally:
        for f in running.values():
            f.cancel()
    for j in range(len(items)):
        ok, value = done[j]
        if not ok:
            raise value
        results[j] = value
    return results


def _collect(forked):
    try:
        return True, forked.result()
    except Exception as exc:                      # noqa: B902
        return False, exc
