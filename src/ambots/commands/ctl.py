"""``python -m ambots ctl pause|resume|stop [ARM|all]``: an operator's
control of a running print (needs the ROS master and the hub; see
:mod:`ambots.control`)."""


def register(sub):
    p = sub.add_parser("ctl", help="pause, resume or stop a running print (one arm or all; needs ROS)",
                       description="Pause (at the end of the current G-code line), stop (brake at once; "
                       "the job is kept) or resume one arm of the running cell, or all of them. The "
                       "command is sent to the communication hub as ROS node /ambots_ctl, which the hub "
                       "must list among its callers (both_arms.launch's callers argument; the default "
                       "does). Waits until the arms have obeyed.")
    p.add_argument("action", choices=("pause", "resume", "stop"))
    p.add_argument("arm", nargs="?", default="all", help="arm name, robot id, or all (default)")
    p.add_argument("--cell", help="cell YAML (default: the running hub's, else the default cell)")
    p.add_argument("--node-name", default="/ambots_ctl",
                   help="ROS node name to send as (default /ambots_ctl; the hub must list it among its callers)")
    p.add_argument("--timeout", type=float, default=60.0,
                   help="seconds to wait for the arms to obey (default 60; 0: do not wait)")
    p.set_defaults(func=run)


def run(args):
    try:
        import rospy  # noqa: F401
    except ImportError:
        from ambots.errors import AmbotsError
        raise AmbotsError("ctl needs ROS (rospy): source env.bash or your ROS setup first") from None
    from ambots.ros.ctl import main
    return main(args.action, args.arm, cell_path=args.cell, timeout=args.timeout, node=args.node_name)
