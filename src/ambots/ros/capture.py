"""Headless capture: RViz on a virtual X screen (Xvfb), screenshot to PNG."""
import os
import subprocess
import time

import rospy
import rosnode


class HeadlessRviz:
    """Starts Xvfb (a free display number) and RViz with ``config``; use as a
    context manager.  :meth:`grab` saves a PNG of RViz's 3D view."""

    def __init__(self, config, size=(1280, 800), node_name="capture_rviz"):
        self.config, self.size, self.node_name = config, size, node_name
        self.xvfb = self.rviz = None
        self.display = None

    def __enter__(self):
        r, w = os.pipe()
        self.xvfb = subprocess.Popen(["Xvfb", "-displayfd", str(w), "-screen", "0",
                                      "%dx%dx24" % self.size, "-nolisten", "tcp"],
                                     pass_fds=(w,), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.close(w)
        with os.fdopen(r) as f:
            self.display = ":" + f.readline().strip()
        env = dict(os.environ, DISPLAY=self.display)
        self.rviz = subprocess.Popen(["rosrun", "rviz", "rviz", "-d", self.config,
                                      "__name:=" + self.node_name],
                                     env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        return self

    def wait_ready(self, timeout=60.0, settle=4.0):
        """Wait until RViz is registered with the master, then ``settle`` s."""
        deadline = time.time() + timeout
        name = "/" + self.node_name
        while time.time() < deadline and not rospy.is_shutdown():
            if self.rviz.poll() is not None:
                raise RuntimeError("rviz exited with code %d" % self.rviz.returncode)
            if name in rosnode.get_node_names():
                time.sleep(settle)
                return
            time.sleep(0.5)
        raise RuntimeError("rviz did not come up within %.0f s" % timeout)

    def grab(self, path, background=(48, 48, 48)):
        """Save a PNG of the 3D view (the area of RViz's background colour)."""
        import numpy as np
        from PIL import ImageGrab
        img = ImageGrab.grab(xdisplay=self.display)
        a = np.asarray(img.convert("RGB"))
        bg = np.all(a == background, axis=2)
        rows, cols = np.where(bg.mean(axis=1) > 0.2)[0], np.where(bg.mean(axis=0) > 0.2)[0]
        if len(rows) and len(cols):
            img = img.crop((cols[0], rows[0], cols[-1] + 1, rows[-1] + 1))
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        img.save(path)
        return path

    def __exit__(self, *exc):
        for p in (self.rviz, self.xvfb):
            if p and p.poll() is None:
                p.terminate()
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
