#!/usr/bin/env python3
"""Check a locally built tf2_msgs (scripts/build_tf2_msgs.sh) end to end.

What is checked (exit status 0 only if all pass):

1. ``from tf2_msgs.msg import TFMessage`` works and its type support loads.
2. The RIHS01 type hash of tf2_msgs/msg/TFMessage equals the released Jazzy
   one (constant below; also recomputed from the definition with
   ``rosbags`` when that is importable), as read from
   a. the generated ``share/tf2_msgs/msg/TFMessage.json`` of the build, and
   b. the ROS graph: the hash rmw advertises for our publisher and for the
      subscriber of the child process (``topic_type_hash`` of
      ``get_{publishers,subscriptions}_info_by_topic``).
3. A latched (transient-local, reliable, depth 1) ``/tf_static`` message
   published *before* the subscriber exists reaches a subscriber node in a
   separate process (so the CDR path through the fastrtps type support is
   exercised), and its frames / translation (m) / rotation quaternion
   (x, y, z, w) arrive unchanged.

Usage (inside the venv)::

    . PREFIX/env.sh && python scripts/check_tf2_msgs.py
    python scripts/check_tf2_msgs.py --prefix PREFIX    # no env.sh needed

``--prefix`` works from inside the process: it puts PREFIX's site-packages
on ``sys.path`` and preloads PREFIX/lib/libtf2_msgs__*.so by full path.
rosidl's type-support dispatch dlopen()s those libraries by bare file name,
which glibc resolves against LD_LIBRARY_PATH as it was at process start (a
later ``os.environ`` change does not count) or against an already loaded
library of that soname, hence the preload; the built libraries carry an RPATH
to each other and to the venv's lib/, so their own dependencies resolve.

ROS_AUTOMATIC_DISCOVERY_RANGE defaults to LOCALHOST and ROS_DOMAIN_ID to 91
unless already set.  Exit codes: 0 ok, 1 check failed, 2 setup/import error.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time

EXPECTED_RIHS01 = (
    'RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087')
TYPE_NAME = 'tf2_msgs/msg/TFMessage'
TOPIC = '/tf_static'

# Two transforms with distinct, non-trivial values (frames, metres, unit quaternions).
SENT = [
    {'parent': 'base_link', 'child': 'laser', 'stamp': (1234, 567890000),
     't_m': (0.125, -0.25, 0.5), 'q_xyzw': (0.0, 0.0, math.sin(0.3), math.cos(0.3))},
    {'parent': 'laser', 'child': 'camera_optical_frame', 'stamp': (1234, 567890000),
     't_m': (0.05, 0.01, -0.02), 'q_xyzw': (-0.5, 0.5, -0.5, 0.5)},
]


def _setup_prefix(prefix: str) -> None:
    """Make a build PREFIX importable from inside this process (no env.sh needed)."""
    import ctypes
    import glob
    prefix = os.path.abspath(prefix)
    site = os.path.join(prefix, 'lib', f'python{sys.version_info[0]}.{sys.version_info[1]}',
                        'site-packages')
    if not os.path.isdir(site):
        raise SystemExit(f'check_tf2_msgs: ERROR: {site} missing; run scripts/build_tf2_msgs.sh '
                         f'{prefix} first')
    sys.path.insert(0, site)
    for var, val in (('LD_LIBRARY_PATH', os.path.join(prefix, 'lib')),
                     ('PYTHONPATH', site), ('AMENT_PREFIX_PATH', prefix)):
        cur = [p for p in os.environ.get(var, '').split(os.pathsep) if p]
        if val not in cur:  # for child processes started from here
            os.environ[var] = os.pathsep.join([val] + cur)
    libs = sorted(glob.glob(os.path.join(prefix, 'lib', 'libtf2_msgs__*.so')))
    if not libs:
        raise SystemExit(f'check_tf2_msgs: ERROR: no libtf2_msgs__*.so in {prefix}/lib')
    for lib in libs:
        ctypes.CDLL(lib, mode=ctypes.RTLD_GLOBAL)


def _import_tfmessage():
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError as exc:
        print(f'check_tf2_msgs: ERROR: cannot import tf2_msgs.msg.TFMessage ({exc}); build it with '
              'scripts/build_tf2_msgs.sh PREFIX and source PREFIX/env.sh or pass --prefix',
              file=sys.stderr)
        sys.exit(2)
    type(TFMessage).__import_type_support__()
    if TFMessage._TYPE_SUPPORT is None:
        print('check_tf2_msgs: ERROR: TFMessage type support did not load', file=sys.stderr)
        sys.exit(2)
    return TFMessage


def _make_msg(TFMessage):
    from geometry_msgs.msg import TransformStamped
    msg = TFMessage()
    for s in SENT:
        ts = TransformStamped()
        ts.header.frame_id = s['parent']
        ts.header.stamp.sec, ts.header.stamp.nanosec = s['stamp']
        ts.child_frame_id = s['child']
        tr, q = ts.transform.translation, ts.transform.rotation
        tr.x, tr.y, tr.z = s['t_m']
        q.x, q.y, q.z, q.w = s['q_xyzw']
        msg.transforms.append(ts)
    return msg


def _msg_to_dicts(msg):
    out = []
    for ts in msg.transforms:
        tr, q = ts.transform.translation, ts.transform.rotation
        out.append({'parent': ts.header.frame_id, 'child': ts.child_frame_id,
                    'stamp': (ts.header.stamp.sec, ts.header.stamp.nanosec),
                    't_m': (tr.x, tr.y, tr.z), 'q_xyzw': (q.x, q.y, q.z, q.w)})
    return out


def _qos():
    from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile,
                           ReliabilityPolicy)
    return QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL,
                      reliability=ReliabilityPolicy.RELIABLE)


def _run_subscriber(timeout_s: float) -> int:
    """Child process: one node, waits for one latched TFMessage, prints it as JSON."""
    TFMessage = _import_tfmessage()
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    got = []
    try:
        node = rclpy.create_node('tf2_msgs_check_sub', context=ctx)
        node.create_subscription(TFMessage, TOPIC, got.append, _qos())
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        deadline = time.monotonic() + timeout_s
        while not got and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.1)
        # Stay a moment so the parent can read our endpoint info from the graph.
        linger_end = time.monotonic() + 1.0
        while time.monotonic() < linger_end:
            ex.spin_once(timeout_sec=0.1)
        ex.shutdown()
        node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
    if not got:
        print(json.dumps({'received': None}))
        return 1
    print(json.dumps({'received': _msg_to_dicts(got[0])}))
    return 0


def _rosbags_hash():
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        return '(rosbags not installed: not compared)'
    try:
        return get_typestore(Stores.ROS2_JAZZY).hash_rihs01(TYPE_NAME)
    except Exception as exc:  # noqa: BLE001 - older rosbags without hash_rihs01
        return f'unavailable ({exc})'


def _generated_hash(TFMessage):
    pkg_dir = os.path.dirname(sys.modules['tf2_msgs'].__file__)
    # PREFIX/lib/pythonX.Y/site-packages/tf2_msgs -> PREFIX
    prefix = os.path.abspath(os.path.join(pkg_dir, '..', '..', '..', '..'))
    path = os.path.join(prefix, 'share', 'tf2_msgs', 'msg', 'TFMessage.json')
    with open(path) as f:
        return json.load(f)['type_hashes'][0]['hash_string'], prefix


def _close(a, b, tol=1e-12):
    return len(a) == len(b) and all(abs(x - y) <= tol for x, y in zip(a, b))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--prefix', help='build PREFIX of scripts/build_tf2_msgs.sh '
                    '(else tf2_msgs must already be importable, e.g. via PREFIX/env.sh)')
    ap.add_argument('--timeout-s', type=float, default=15.0,
                    help='seconds to wait for discovery and delivery (default 15)')
    ap.add_argument('--subscriber', action='store_true', help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    os.environ.setdefault('ROS_DOMAIN_ID', '91')
    if args.prefix:
        _setup_prefix(args.prefix)
    if args.subscriber:
        return _run_subscriber(args.timeout_s)

    t_start = time.monotonic()
    TFMessage = _import_tfmessage()
    failures = []

    # ---- type hash: constant vs rosbags vs generated JSON
    gen_hash, prefix = _generated_hash(TFMessage)
    rb_hash = _rosbags_hash()
    print(f'tf2_msgs from      : {prefix}')
    print(f'expected (Jazzy)   : {EXPECTED_RIHS01}')
    print(f'rosbags ROS2_JAZZY : {rb_hash}')
    print(f'generated JSON     : {gen_hash}')
    if gen_hash != EXPECTED_RIHS01:
        failures.append(f'generated hash {gen_hash} != expected')
    if rb_hash.startswith('RIHS01_') and rb_hash != EXPECTED_RIHS01:
        failures.append(f'rosbags hash {rb_hash} != expected constant')

    # ---- pub (this process, latched, published before the subscriber exists)
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    child = None
    try:
        node = rclpy.create_node('tf2_msgs_check_pub', context=ctx)
        pub = node.create_publisher(TFMessage, TOPIC, _qos())
        pub.publish(_make_msg(TFMessage))
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)

        cmd = [sys.executable, os.path.abspath(__file__), '--subscriber',
               '--timeout-s', str(args.timeout_s)]
        if args.prefix:
            cmd += ['--prefix', args.prefix]
        child = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                 text=True, env=os.environ.copy())

        # While the child runs, read the graph: our publisher and its subscriber.
        graph_hashes = {}
        deadline = time.monotonic() + args.timeout_s + 5.0
        while child.poll() is None and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.1)
            for kind, infos in (('publisher', node.get_publishers_info_by_topic(TOPIC)),
                                ('subscriber', node.get_subscriptions_info_by_topic(TOPIC))):
                for info in infos:
                    if info.node_name == '_NODE_NAME_UNKNOWN_':  # not yet discovered fully
                        continue
                    graph_hashes[(kind, info.node_name)] = (info.topic_type,
                                                            str(info.topic_type_hash))
        try:
            out, err = child.communicate(timeout=max(1.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            child.kill()
            out, err = child.communicate()
            failures.append('subscriber process timed out')
        ex.shutdown()
        node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)

    for (kind, name), (ttype, thash) in sorted(graph_hashes.items()):
        print(f'graph {kind:10s} {name:22s}: {ttype} {thash}')
        if ttype != TYPE_NAME or thash != EXPECTED_RIHS01:
            failures.append(f'graph {kind} {name}: {ttype} {thash}')
    for want in (('publisher', 'tf2_msgs_check_pub'), ('subscriber', 'tf2_msgs_check_sub')):
        if want not in graph_hashes:
            failures.append(f'{want[0]} {want[1]} never seen in the graph')

    # ---- delivery and content
    received = None
    try:
        received = json.loads(out.strip().splitlines()[-1])['received'] if out.strip() else None
    except (ValueError, KeyError, IndexError):
        pass
    if received is None:
        failures.append(f'subscriber received nothing (rc={child.returncode}); '
                        f'stderr tail: {err.strip()[-800:]}')
    else:
        print(f'received {len(received)} transforms on {TOPIC} in the subscriber process')
        if len(received) != len(SENT):
            failures.append(f'received {len(received)} transforms, sent {len(SENT)}')
        for s, r in zip(SENT, received):
            ok = (s['parent'] == r['parent'] and s['child'] == r['child']
                  and tuple(s['stamp']) == tuple(r['stamp'])
                  and _close(s['t_m'], r['t_m']) and _close(s['q_xyzw'], r['q_xyzw']))
            if not ok:
                failures.append(f'content mismatch: sent {s}, received {r}')

    print(f'elapsed {time.monotonic() - t_start:.1f} s')
    if failures:
        for f in failures:
            print(f'check_tf2_msgs: FAIL: {f}', file=sys.stderr)
        return 1
    print('check_tf2_msgs: OK')
    return 0


if __name__ == '__main__':
    sys.exit(main())
