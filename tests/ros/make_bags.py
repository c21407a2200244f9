#!/usr/bin/env python3
"""Write ROS 2 bags for voxmap's tests and benchmark with independent writers: the
`rosbags` library (rosbag2 in sqlite3 and MCAP, its CDR serializer) and Foxglove's `mcap`
writer (lz4 chunks). Nothing here uses voxmap's code.

    make_bags.py tum FRAMES_DIR OUT_DIR    the TUM frames (KITTI .bin named by stamp, and
                                           poses.txt in TUM format) as a TF tree, mixed
                                           cloud layouts, in three storages
    make_bags.py bad OUT_DIR               clouds and transforms that are wrong in each way
    make_bags.py bench N POINTS OUT_DIR    N lidar-like clouds as a bag and as PCD files
"""
import math
import sys
from decimal import Decimal
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import Writer, StoragePlugin
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
from rosbags.typesys import Stores, get_typestore

TS = get_typestore(Stores.ROS2_JAZZY)
T = TS.types
PC2 = 'sensor_msgs/msg/PointCloud2'
TFM = 'tf2_msgs/msg/TFMessage'
ODOM = 'nav_msgs/msg/Odometry'
F32, F64, U16, U32 = 7, 8, 4, 6

# ---- quaternions as (x, y, z, w) tuples of floats ----


def qmul(a, b):
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz)


def qconj(q):
    return (-q[0], -q[1], -q[2], q[3])


def qrot(q, v):
    x, y, z, _ = qmul(qmul(q, (v[0], v[1], v[2], 0.0)), qconj(q))
    return (x, y, z)


def qaxis(axis, angle):
    s = math.sin(angle / 2)
    n = math.sqrt(sum(c * c for c in axis))
    return (axis[0] / n * s, axis[1] / n * s, axis[2] / n * s, math.cos(angle / 2))


# A pose is (t, q): it maps p to q p q* + t.
def compose(a, b):
    ta, qa = a
    tb, qb = b
    r = qrot(qa, tb)
    return ((ta[0] + r[0], ta[1] + r[1], ta[2] + r[2]), qmul(qa, qb))


def inverse(a):
    t, q = a
    qi = qconj(q)
    r = qrot(qi, t)
    return ((-r[0], -r[1], -r[2]), qi)


# ---- messages ----


def stamp(ns):
    return T['builtin_interfaces/msg/Time'](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def header(ns, frame):
    return T['std_msgs/msg/Header'](stamp=stamp(ns), frame_id=frame)


def transform_stamped(ns, parent, child, pose):
    t, q = pose
    return T['geometry_msgs/msg/TransformStamped'](
        header=header(ns, parent), child_frame_id=child,
        transform=T['geometry_msgs/msg/Transform'](
            translation=T['geometry_msgs/msg/Vector3'](x=t[0], y=t[1], z=t[2]),
            rotation=T['geometry_msgs/msg/Quaternion'](x=q[0], y=q[1], z=q[2], w=q[3])))


def tf_message(transforms):
    return T[TFM](transforms=transforms)


def odometry(ns, parent, child, pose):
    t, q = pose
    p = T['geometry_msgs/msg/Pose'](
        position=T['geometry_msgs/msg/Point'](x=t[0], y=t[1], z=t[2]),
        orientation=T['geometry_msgs/msg/Quaternion'](x=q[0], y=q[1], z=q[2], w=q[3]))
    cov = np.zeros(36, dtype=np.float64)
    zero = T['geometry_msgs/msg/Vector3'](x=0.0, y=0.0, z=0.0)
    return T[ODOM](
        header=header(ns, parent), child_frame_id=child,
        pose=T['geometry_msgs/msg/PoseWithCovariance'](pose=p, covariance=cov),
        twist=T['geometry_msgs/msg/TwistWithCovariance'](
            twist=T['geometry_msgs/msg/Twist'](linear=zero, angular=zero), covariance=cov))


def field(name, offset, datatype):
    return T['sensor_msgs/msg/PointField'](name=name, offset=offset, datatype=datatype, count=1)


def cloud(ns, frame, fields, height, width, point_step, row_step, data, is_dense, big=False):
    return T[PC2](header=header(ns, frame), height=height, width=width, fields=fields,
                  is_bigendian=big, point_step=point_step, row_step=row_step,
                  data=np.frombuffer(bytes(data), dtype=np.uint8), is_dense=is_dense)


def with_gaps(xyz, every, width):
    """Organized: a NaN point after every `every`-th point, an infinite one first, padded
    with NaN to whole rows of `width`."""
    rows = [np.array([[np.inf, 0.0, 0.0]], dtype=np.float32)]
    for i in range(0, len(xyz), every):
        rows.append(xyz[i:i + every])
        rows.append(np.full((1, 3), np.nan, dtype=np.float32))
    out = np.concatenate(rows)
    pad = (-len(out)) % width
    out = np.concatenate([out, np.full((pad, 3), np.nan, dtype=np.float32)])
    return out, len(out) // width


def layout(k, xyz, ns, frame):
    """Cloud k of the TUM bag: six layouts met in the wild, in turn."""
    n = len(xyz)
    kind = k % 6
    if kind == 0:  # PCL's PointXYZRGB: x y z, rgb packed in a float, 16 bytes
        rec = np.zeros(n, dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('rgb', '<f4')])
        rec['x'], rec['y'], rec['z'] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        rec['rgb'] = 1.5
        f = [field('x', 0, F32), field('y', 4, F32), field('z', 8, F32), field('rgb', 12, F32)]
        return cloud(ns, frame, f, 1, n, 16, 16 * n, rec.tobytes(), True)
    if kind == 1:  # organized 640 wide, NaN and inf points, is_dense false
        pts, h = with_gaps(xyz, 7, 640)
        rec = np.zeros(len(pts), dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('_', '<f4')])
        rec['x'], rec['y'], rec['z'] = pts[:, 0], pts[:, 1], pts[:, 2]
        f = [field('x', 0, F32), field('y', 4, F32), field('z', 8, F32)]
        return cloud(ns, frame, f, h, 640, 16, 16 * 640, rec.tobytes(), False)
    if kind == 2:  # float64, the field list in another order than the bytes, padding
        rec = np.zeros(n, dtype=[('intensity', '<f4'), ('_', '<u4'), ('z', '<f8'), ('y', '<f8'),
                                 ('x', '<f8'), ('__', '<u8')])
        rec['x'], rec['y'], rec['z'] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        rec['intensity'] = 100.0
        f = [field('intensity', 0, F32), field('z', 8, F64), field('y', 16, F64), field('x', 24, F64)]
        return cloud(ns, frame, f, 1, n, 40, 40 * n, rec.tobytes(), True)
    if kind == 3:  # big-endian data
        rec = np.zeros(n, dtype=[('x', '>f4'), ('y', '>f4'), ('z', '>f4')])
        rec['x'], rec['y'], rec['z'] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        f = [field('x', 0, F32), field('y', 4, F32), field('z', 8, F32)]
        return cloud(ns, frame, f, 1, n, 12, 12 * n, rec.tobytes(), True, big=True)
    if kind == 4:  # organized 320 wide with 64 bytes of padding at the end of each row
        pts, h = with_gaps(xyz, 11, 320)
        rec = np.zeros(len(pts), dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('_', '<f4')])
        rec['x'], rec['y'], rec['z'] = pts[:, 0], pts[:, 1], pts[:, 2]
        rows = rec.tobytes()
        step, rs = 16, 16 * 320 + 64
        data = bytearray()
        for r in range(h):
            data += rows[r * step * 320:(r + 1) * step * 320] + b'\xee' * 64
        f = [field('x', 0, F32), field('y', 4, F32), field('z', 8, F32)]
        return cloud(ns, frame, f, h, 320, step, rs, data, False)
    # Ouster-like: x y z, padding, intensity, t, reflectivity, ring, ambient; 48 bytes
    rec = np.zeros(n, dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('_', '<f4'),
                             ('intensity', '<f4'), ('t', '<u4'), ('reflectivity', '<u2'),
                             ('ring', '<u2'), ('ambient', '<u2'), ('__', 'V18')])
    rec['x'], rec['y'], rec['z'] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rec['ring'] = np.arange(n) % 64
    f = [field('x', 0, F32), field('y', 4, F32), field('z', 8, F32), field('intensity', 16, F32),
         field('t', 20, U32), field('reflectivity', 24, U16), field('ring', 26, U16),
         field('ambient', 28, U16)]
    return cloud(ns, frame, f, 1, n, 48, 48 * n, rec.tobytes(), True)


# ---- writers: a list of (topic, type, log_time_ns, message, little_endian) ----


def write_rosbag(path, messages, storage, zstd=False):
    """rosbag2 by `rosbags`; `zstd`: MCAP with zstd chunks (rosbags' storage compression)."""
    w = Writer(path, version=9, storage_plugin=storage)
    if zstd:
        w.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with w:
        conns = {}
        for topic, typ, _, _, _ in messages:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, typ, typestore=TS)
        for topic, typ, t, msg, le in messages:
            w.write(conns[topic], t, bytes(TS.serialize_cdr(msg, typ, little_endian=le)))


def write_mcap_lz4(path, messages, chunk_size=1 << 18):
    from mcap.writer import Writer as McapWriter, CompressionType
    with open(path, 'wb') as f:
        w = McapWriter(f, chunk_size=chunk_size, compression=CompressionType.LZ4)
        w.start(profile='ros2', library='voxmap-tests')
        schemas, channels = {}, {}
        for topic, typ, _, _, _ in messages:
            if typ not in schemas:
                text, _ = TS.generate_msgdef(typ, ros_version=2)
                schemas[typ] = w.register_schema(name=typ, encoding='ros2msg', data=text.encode())
            if topic not in channels:
                channels[topic] = w.register_channel(topic=topic, message_encoding='cdr',
                                                     schema_id=schemas[typ])
        for seq, (topic, typ, t, msg, le) in enumerate(messages):
            w.add_message(channel_id=channels[topic], log_time=t, publish_time=t, sequence=seq,
                          data=bytes(TS.serialize_cdr(msg, typ, little_endian=le)))
        w.finish()


# ---- the TUM bags ----

# The optical frame's pose T in the world is split as map->odom (static) * odom->base
# (dynamic) * base->camera_link (static) * camera_link->optical (static, ROS's optical
# rotation). odom->base is sampled 10 ms either side of each cloud, moved off D by a twist
# that the halfway interpolation undoes.
MAP_ODOM = ((1.0, 2.0, 0.0), qaxis((0, 0, 1), math.radians(30)))
BASE_CAM = ((0.2, 0.0, 0.5), qaxis((0, 1, 0), math.radians(5)))
CAM_OPT = ((0.0, 0.0, 0.0), (-0.5, 0.5, -0.5, 0.5))
HALF = 10_000_000
OPT = 'camera_rgb_optical_frame'


def tum_messages(frames_dir):
    frames_dir = Path(frames_dir)
    poses = {}
    for line in (frames_dir / 'poses.txt').read_text().split('\n'):
        w = line.split()
        if len(w) == 8:
            # TUM writes quaternions to four decimals: normalise, as every reader does.
            q = [float(c) for c in w[4:8]]
            n = math.sqrt(sum(c * c for c in q))
            poses[w[0]] = ((float(w[1]), float(w[2]), float(w[3])), tuple(c / n for c in q))
    bins = sorted(frames_dir.glob('*.bin'))
    stamps = [int(Decimal(b.stem) * 10**9) for b in bins]
    msgs = []
    t0 = stamps[0] - 100_000_000
    # Static links once at the start; one of them serialized big-endian.
    msgs.append(('/tf_static', TFM, t0, tf_message([
        transform_stamped(t0, 'map', 'odom', MAP_ODOM),
        transform_stamped(t0, 'base_link', 'camera_link', BASE_CAM)]), True))
    msgs.append(('/tf_static', TFM, t0 + 1, tf_message([
        transform_stamped(t0, 'camera_link', OPT, CAM_OPT)]), False))
    events = []
    for k, (b, ns) in enumerate(zip(bins, stamps)):
        xyz = np.fromfile(b, dtype='<f4').reshape(-1, 4)[:, :3].copy()
        T_ = poses[b.stem]
        # D = M^-1 T (B C)^-1
        d = compose(compose(inverse(MAP_ODOM), T_), inverse(compose(BASE_CAM, CAM_OPT)))
        twist_q = qaxis((0.3, -0.2, 1.0), 0.02)
        shift = (0.01, -0.02, 0.005)
        before = ((d[0][0] - shift[0], d[0][1] - shift[1], d[0][2] - shift[2]), qmul(d[1], qconj(twist_q)))
        after = ((d[0][0] + shift[0], d[0][1] + shift[1], d[0][2] + shift[2]), qmul(d[1], twist_q))
        for when, p in ((ns - HALF, before), (ns + HALF, after)):
            events.append((when + 1_000_000, '/tf', TFM,
                           tf_message([transform_stamped(when, 'odom', 'base_link', p)]), True))
            events.append((when + 1_000_000, '/odom', ODOM, odometry(when, 'odom', 'base_link', p), True))
        # The cloud is recorded 5 ms after its stamp, before the sample after it.
        events.append((ns + 5_000_000, '/camera/depth/points', PC2, layout(k, xyz, ns, OPT), True))
    events.sort(key=lambda e: e[0])
    msgs += [(topic, typ, t, m, le) for t, topic, typ, m, le in events]
    return msgs


def make_tum(frames_dir, out):
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    msgs = tum_messages(frames_dir)
    write_rosbag(out / 'sqlite', msgs, StoragePlugin.SQLITE3)
    write_rosbag(out / 'mcap_zstd', msgs, StoragePlugin.MCAP, zstd=True)
    write_mcap_lz4(out / 'lz4.mcap', msgs)


# ---- the bad bag ----


def xyz_cloud(ns, frame, xyz):
    rec = np.asarray(xyz, dtype='<f4')
    f = [field('x', 0, F32), field('y', 4, F32), field('z', 8, F32)]
    return cloud(ns, frame, f, 1, len(rec), 12, 12 * len(rec), rec.tobytes(), True)


def make_bad(out):
    """Ten seconds of odom->base at 10 Hz (from t = 100 s to 110 s), map->odom and
    base->lidar static; clouds 0, 7 and 9 good, every other one wrong in its own way."""
    s = 1_000_000_000
    ring = [[3.0 * math.cos(a), 3.0 * math.sin(a), 0.2] for a in np.linspace(0, 2 * math.pi, 360, endpoint=False)]
    ident = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    msgs = [('/tf_static', TFM, 100 * s, tf_message([
        transform_stamped(0, 'map', 'odom', ident),
        transform_stamped(0, 'base_link', 'lidar', ((0.0, 0.0, 1.0), (0.0, 0.0, 0.0, 1.0)))]), True)]
    for i in range(101):
        t = 100 * s + i * s // 10
        msgs.append(('/tf', TFM, t, tf_message([
            transform_stamped(t, 'odom', 'base_link', ((0.1 * i, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)))]), True))
    # Two transforms tf2 would refuse: a NaN translation and a zero quaternion.
    msgs.append(('/tf', TFM, 100 * s + 1, tf_message([
        transform_stamped(100 * s, 'odom', 'x1', ((math.nan, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))),
        transform_stamped(100 * s, 'odom', 'x2', ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0)))]), True))

    good = lambda t: xyz_cloud(t, 'lidar', ring)
    clouds = []
    t = 101 * s
    clouds.append((t, good(t)))                                              # 0 good
    c = good(t + s // 10)
    c.fields = c.fields[:2]                                                  # 1 no z
    clouds.append((t + s // 10, c))
    c = good(t + 2 * s // 10)
    c.data = c.data[:-12]                                                    # 2 data short
    clouds.append((t + 2 * s // 10, c))
    c = good(t + 3 * s // 10)
    c.fields[0].datatype = 3                                                 # 3 x is INT16
    clouds.append((t + 3 * s // 10, c))
    clouds.append((t + 4 * s // 10, xyz_cloud(t + 4 * s // 10, 'nowhere', ring)))  # 4 unknown frame
    clouds.append((t + 5 * s // 10, xyz_cloud(120 * s, 'lidar', ring)))           # 5 future
    clouds.append((t + 6 * s // 10, xyz_cloud(90 * s, 'lidar', ring)))            # 6 past
    clouds.append((t + 7 * s // 10, good(t + 7 * s // 10)))                  # 7 good
    c = good(t + 8 * s // 10)
    c.row_step = 100                                                         # 8 row_step short
    clouds.append((t + 8 * s // 10, c))
    nan_ring = [p if i % 3 else [math.nan] * 3 for i, p in enumerate(ring)]
    c = xyz_cloud(t + 9 * s // 10, 'lidar', nan_ring)
    c.is_dense = False
    clouds.append((t + 9 * s // 10, c))                                      # 9 good, 120 NaN
    for log, c in clouds:
        msgs.append(('/lidar/points', PC2, log + 1, c, True))
    msgs.sort(key=lambda m: m[2])
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_rosbag(out / 'bad', msgs, StoragePlugin.MCAP)
    # A message on the cloud topic that is not a PointCloud2: written raw.
    from mcap.writer import Writer as McapWriter, CompressionType
    with open(out / 'garbage.mcap', 'wb') as f:
        w = McapWriter(f, compression=CompressionType.NONE)
        w.start(profile='ros2', library='voxmap-tests')
        text, _ = TS.generate_msgdef(PC2, ros_version=2)
        sid = w.register_schema(name=PC2, encoding='ros2msg', data=text.encode())
        cid = w.register_channel(topic='/lidar/points', message_encoding='cdr', schema_id=sid)
        w.add_message(channel_id=cid, log_time=1, publish_time=1, sequence=0,
                      data=b'\x00\x01\x00\x00\xff\xff\xff\xff')
        w.finish()
    # Two PointCloud2 topics: replay must be told which.
    two = [('/front/points', PC2, 1, good(1), True), ('/rear/points', PC2, 2, good(2), True)]
    write_mcap_lz4(out / 'two_topics.mcap', two)


# ---- the benchmark bag ----


def make_bench(n, points, out):
    """N clouds of a 64-beam spinning lidar (POINTS points each) in a 30 m room, Ouster
    layout, the sensor driving along x, /tf at 100 Hz; as an MCAP bag (zstd chunks, as `ros2 bag
    record --storage-preset-profile zstd_fast`), a sqlite3 bag, and binary PCD files with
    VIEWPOINT."""
    out = Path(out)
    (out / 'pcd').mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(7)
    s = 1_000_000_000
    msgs = [('/tf_static', TFM, s, tf_message([
        transform_stamped(0, 'base_link', 'os_sensor', ((0.0, 0.0, 1.2), (0.0, 0.0, 0.0, 1.0)))]), True)]
    beams = 64
    cols = points // beams
    el = np.radians(np.linspace(-22.5, 22.5, beams))[:, None]
    az = np.linspace(0, 2 * np.pi, cols, endpoint=False)[None, :]
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) + 0 * az], -1).reshape(-1, 3)
    for k in range(n):
        ns = 2 * s + k * s // 10
        x = 0.05 * k
        # Ranges to the walls of a 30 x 20 x 6 m box around (0,0,0), with noise.
        o = np.array([x, 0.0, 1.2])
        lo, hi = np.array([-15.0, -10.0, 0.0]), np.array([15.0, 10.0, 6.0])
        with np.errstate(divide='ignore', invalid='ignore'):
            t1, t2 = (lo - o) / d, (hi - o) / d
        r = np.nanmin(np.where(np.maximum(t1, t2) > 0, np.maximum(t1, t2), np.inf), axis=1)
        r = r * (1 + 0.002 * rng.standard_normal(len(r)))
        xyz = (d * r[:, None]).astype(np.float32)
        # The driver hands the cloud over 20 ms after its stamp.
        msgs.append(('/os/points', PC2, ns + 20_000_000, layout(5, xyz, ns, 'os_sensor'), True))
        head = ('# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n'
                f'WIDTH {len(xyz)}\nHEIGHT 1\nVIEWPOINT {x!r} 0 1.2 1 0 0 0\nPOINTS {len(xyz)}\nDATA binary\n')
        (out / 'pcd' / f'{k:04d}.pcd').write_bytes(head.encode() + xyz.astype('<f4').tobytes())
    # Odometry on /tf at 100 Hz, recorded as stamped, from 0.5 s before the first cloud to
    # 0.5 s after the last: base_link drives along x at 0.5 m/s.
    for j in range(10 * n + 100):
        ns = 2 * s - s // 2 + j * s // 100
        x = 0.05 * ((j - 50) / 10)
        msgs.append(('/tf', TFM, ns, tf_message([transform_stamped(
            ns, 'map', 'base_link', ((x, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)))]), True))
    msgs.sort(key=lambda m: m[2])
    write_rosbag(out / 'bag', msgs, StoragePlugin.MCAP, zstd=True)
    write_rosbag(out / 'bag_sqlite', msgs, StoragePlugin.SQLITE3)


if __name__ == '__main__':
    cmd = sys.argv[1]
    if cmd == 'tum':
        make_tum(sys.argv[2], sys.argv[3])
    elif cmd == 'bad':
        make_bad(sys.argv[2])
    elif cmd == 'bench':
        make_bench(int(sys.argv[2]), int(sys.argv[3]), sys.argv[4])
    else:
        sys.exit(__doc__)
