#!/usr/bin/env python3
"""A ROS 2 peer for voxmap's live bridge that voxmap did not write: Cyclone DDS (PyPI
`cyclonedds`, its bundled C library) with the ROS 2 message types declared for it as ROS 2's
DDS RMWs name them, and the messages made by `rosbags` (make_bags.py's TUM scene). Nothing
here uses voxmap's code.

    ros2_peer.py publish FRAMES_DIR OUT_DIR   publish the TUM scene (clouds in the optical
        frame, poses only in /tf and /tf_static), then a cloud with no transform and a
        malformed cloud; wait for /voxmap/occupied and /voxmap/octomap_binary stamped with
        the last cloud; call the services; write what came back to OUT_DIR
    ros2_peer.py listen OUT_DIR               join late: take the latched map topics
    ros2_peer.py cyclone-reset OUT_DIR        call reset_map as rmw_cyclonedds_cpp does:
        a request header (8 bytes of the client GUID, a 64-bit sequence number) before
        the request, echoed before the reply

Discovery: loopback only, unicast to 127.0.0.1 (CYCLONEDDS_URI set here unless given), on
ROS_DOMAIN_ID.
"""
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

if 'CYCLONEDDS_URI' not in os.environ:
    os.environ['CYCLONEDDS_URI'] = (
        '<CycloneDDS><Domain id="any"><General><Interfaces>'
        '<NetworkInterface name="lo"/></Interfaces>'
        '<AllowMulticast>false</AllowMulticast></General>'
        '<Discovery><ParticipantIndex>auto</ParticipantIndex>'
        '<MaxAutoParticipantIndex>20</MaxAutoParticipantIndex>'
        '<Peers><Peer address="127.0.0.1"/></Peers></Discovery>'
        '</Domain></CycloneDDS>')

from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import array, float32, float64, int32, int8, sequence, uint32, uint8
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

sys.path.insert(0, str(Path(__file__).parent))
import make_bags  # noqa: E402  (the TUM scene as rosbags messages)


@dataclass
class Time(IdlStruct, typename='builtin_interfaces::msg::dds_::Time_'):
    sec: int32
    nanosec: uint32


@dataclass
class Header(IdlStruct, typename='std_msgs::msg::dds_::Header_'):
    stamp: Time
    frame_id: str


@dataclass
class PointField(IdlStruct, typename='sensor_msgs::msg::dds_::PointField_'):
    name: str
    offset: uint32
    datatype: uint8
    count: uint32


@dataclass
class PointCloud2(IdlStruct, typename='sensor_msgs::msg::dds_::PointCloud2_'):
    header: Header
    height: uint32
    width: uint32
    fields: sequence[PointField]
    is_bigendian: bool
    point_step: uint32
    row_step: uint32
    data: sequence[uint8]
    is_dense: bool


@dataclass
class Vector3(IdlStruct, typename='geometry_msgs::msg::dds_::Vector3_'):
    x: float64
    y: float64
    z: float64


@dataclass
class Point(IdlStruct, typename='geometry_msgs::msg::dds_::Point_'):
    x: float64
    y: float64
    z: float64


@dataclass
class Quaternion(IdlStruct, typename='geometry_msgs::msg::dds_::Quaternion_'):
    x: float64
    y: float64
    z: float64
    w: float64


@dataclass
class Transform(IdlStruct, typename='geometry_msgs::msg::dds_::Transform_'):
    translation: Vector3
    rotation: Quaternion


@dataclass
class TransformStamped(IdlStruct, typename='geometry_msgs::msg::dds_::TransformStamped_'):
    header: Header
    child_frame_id: str
    transform: Transform


@dataclass
class TFMessage(IdlStruct, typename='tf2_msgs::msg::dds_::TFMessage_'):
    transforms: sequence[TransformStamped]


@dataclass
class Octomap(IdlStruct, typename='octomap_msgs::msg::dds_::Octomap_'):
    header: Header
    binary: bool
    id: str
    resolution: float64
    data: sequence[int8]


@dataclass
class Pose(IdlStruct, typename='geometry_msgs::msg::dds_::Pose_'):
    position: Point
    orientation: Quaternion


@dataclass
class MapMetaData(IdlStruct, typename='nav_msgs::msg::dds_::MapMetaData_'):
    map_load_time: Time
    resolution: float32
    width: uint32
    height: uint32
    origin: Pose


@dataclass
class OccupancyGrid(IdlStruct, typename='nav_msgs::msg::dds_::OccupancyGrid_'):
    header: Header
    info: MapMetaData
    data: sequence[int8]


@dataclass
class TriggerRequest(IdlStruct, typename='std_srvs::srv::dds_::Trigger_Request_'):
    structure_needs_at_least_one_member: uint8


@dataclass
class TriggerResponse(IdlStruct, typename='std_srvs::srv::dds_::Trigger_Response_'):
    success: bool
    message: str


@dataclass
class SaveMapRequest(IdlStruct, typename='voxmap_msgs::srv::dds_::SaveMap_Request_'):
    path: str


@dataclass
class SaveMapResponse(IdlStruct, typename='voxmap_msgs::srv::dds_::SaveMap_Response_'):
    success: bool
    message: str


@dataclass
class LoadMapRequest(IdlStruct, typename='voxmap_msgs::srv::dds_::LoadMap_Request_'):
    path: str


@dataclass
class LoadMapResponse(IdlStruct, typename='voxmap_msgs::srv::dds_::LoadMap_Response_'):
    success: bool
    message: str


@dataclass
class RaytraceRequest(IdlStruct, typename='voxmap_msgs::srv::dds_::Raytrace_Request_'):
    origin: Point
    direction: Vector3
    max_length: float64


@dataclass
class RaytraceResponse(IdlStruct, typename='voxmap_msgs::srv::dds_::Raytrace_Response_'):
    success: bool
    hit: bool
    end_point: Point
    message: str


@dataclass
class CycloneTriggerRequest(IdlStruct, typename='std_srvs::srv::dds_::Trigger_Request_'):
    client_guid_low: array[uint8, 8]
    sequence_high: int32
    sequence_low: uint32
    structure_needs_at_least_one_member: uint8


@dataclass
class CycloneTriggerResponse(IdlStruct, typename='std_srvs::srv::dds_::Trigger_Response_'):
    client_guid_low: array[uint8, 8]
    sequence_high: int32
    sequence_low: uint32
    success: bool
    message: str


DOMAIN = int(os.environ.get('ROS_DOMAIN_ID', '0'))
RELIABLE = Policy.Reliability.Reliable(duration(seconds=1))
LATCHED = Qos(RELIABLE, Policy.Durability.TransientLocal, Policy.History.KeepLast(1))
SENSOR = Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(5))
TF = Qos(RELIABLE, Policy.History.KeepLast(100))
TF_STATIC = Qos(RELIABLE, Policy.Durability.TransientLocal, Policy.History.KeepLast(1))
SERVICE = Qos(RELIABLE, Policy.History.KeepLast(10))


def cyclone(msg, typ, cls, little_endian=True):
    """A rosbags message as the Cyclone type: rosbags' CDR bytes read by Cyclone."""
    return cls.deserialize(bytes(make_bags.TS.serialize_cdr(msg, typ, little_endian=little_endian)))


def wait_matched(writer, what, timeout=20.0):
    end = time.time() + timeout
    while time.time() < end:
        if writer.get_matched_subscriptions():
            return
        time.sleep(0.05)
    raise SystemExit(f'{what}: no subscriber matched in {timeout} s')


def map_readers(dp):
    return (DataReader(dp, Topic(dp, 'rt/voxmap/occupied', PointCloud2), qos=LATCHED),
            DataReader(dp, Topic(dp, 'rt/voxmap/octomap_binary', Octomap), qos=LATCHED),
            DataReader(dp, Topic(dp, 'rt/voxmap/grid', OccupancyGrid), qos=LATCHED))


def take_maps(readers, want_ns, timeout=60.0, want=None):
    """The newest of each map topic once all three are stamped `want_ns` (and, if given,
    `want(occupied)` holds)."""
    newest = [None, None, None]
    end = time.time() + timeout
    while time.time() < end:
        for i, r in enumerate(readers):
            for s in r.take(N=100):
                newest[i] = s
        ok = all(m is not None and m.header.stamp.sec * 10**9 + m.header.stamp.nanosec == want_ns
                 for m in newest)
        if ok and (want is None or want(newest[0])):
            return newest
        time.sleep(0.05)
    stamps = [None if m is None else (m.header.stamp.sec, m.header.stamp.nanosec) for m in newest]
    raise SystemExit(f'map topics stamped {want_ns} not received in {timeout} s: {stamps}')


def write_maps(out, maps, tag):
    occ, octo, grid = maps
    Path(out, f'{tag}_occupied.bin').write_bytes(bytes(occ.data))
    Path(out, f'{tag}_octomap.bin').write_bytes(bytes(b & 0xff for b in octo.data))
    Path(out, f'{tag}_grid.bin').write_bytes(bytes(b & 0xff for b in grid.data))
    o = grid.info.origin.position
    return {
        'occupied': {'width': occ.width, 'height': occ.height, 'point_step': occ.point_step,
                     'frame': occ.header.frame_id, 'fields': [(f.name, f.offset, f.datatype) for f in occ.fields]},
        'octomap': {'binary': octo.binary, 'id': octo.id, 'resolution': octo.resolution,
                    'frame': octo.header.frame_id},
        'grid': {'width': grid.info.width, 'height': grid.info.height,
                 'resolution': grid.info.resolution, 'origin': [o.x, o.y, o.z]},
    }


class Service:
    """A plain request writer and reply reader on the rq/ and rr/ topics (one client at a
    time, so replies need no matching to requests)."""

    def __init__(self, dp, name, req, resp):
        self.w = DataWriter(dp, Topic(dp, f'rq/voxmap/{name}Request', req), qos=SERVICE)
        self.r = DataReader(dp, Topic(dp, f'rr/voxmap/{name}Reply', resp), qos=SERVICE)
        self.name = name

    def call(self, request, timeout=30.0):
        end = time.time() + timeout
        while not (self.w.get_matched_subscriptions() and self.r.get_matched_publications()):
            if time.time() > end:
                raise SystemExit(f'service {self.name}: server not matched')
            time.sleep(0.05)
        time.sleep(0.2)
        self.w.write(request)
        while time.time() < end:
            got = self.r.take(N=1)
            if got:
                return got[0]
            time.sleep(0.02)
        raise SystemExit(f'service {self.name}: no reply in {timeout} s')


def publish(frames_dir, out):
    dp = DomainParticipant(DOMAIN)
    w_cloud = DataWriter(dp, Topic(dp, 'rt/camera/depth/points', PointCloud2), qos=SENSOR)
    w_tf = DataWriter(dp, Topic(dp, 'rt/tf', TFMessage), qos=TF)
    w_static = DataWriter(dp, Topic(dp, 'rt/tf_static', TFMessage), qos=TF_STATIC)
    readers = map_readers(dp)
    for w, what in ((w_cloud, 'cloud'), (w_tf, '/tf')):
        wait_matched(w, what)
    time.sleep(0.5)
    statics = []
    last_ns = None
    clouds = 0
    for topic, typ, _, msg, le in make_bags.tum_messages(frames_dir):
        if topic == '/tf_static':
            # One latched message with every static link, as tf2's static broadcaster sends.
            statics += cyclone(msg, typ, TFMessage, le).transforms
            w_static.write(TFMessage(transforms=statics))
        elif topic == '/tf':
            w_tf.write(cyclone(msg, typ, TFMessage, le))
        elif topic == '/camera/depth/points':
            w_cloud.write(cyclone(msg, typ, PointCloud2, le))
            last_ns = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            clouds += 1
            # Paced as a camera: the service integrates each before the next.
            time.sleep(0.15)
    # A cloud in a frame no transform reaches, and one whose data is shorter than it says.
    fields = [PointField('x', 0, 7, 1), PointField('y', 4, 7, 1), PointField('z', 8, 7, 1)]
    last = Time(last_ns // 10**9, last_ns % 10**9)
    w_cloud.write(PointCloud2(Header(last, 'nowhere'), 1, 2, fields, False, 12, 24, [0] * 24, True))
    time.sleep(0.15)
    w_cloud.write(PointCloud2(Header(last, make_bags.OPT), 1, 4, fields, False, 12, 48, [0] * 24, True))

    result = {'clouds': clouds, 'last_ns': last_ns}
    maps = take_maps(readers, last_ns)
    result['first'] = write_maps(out, maps, 'first')

    # Services, as a ROS 2 client would call them.
    save = Service(dp, 'save_map', SaveMapRequest, SaveMapResponse)
    load = Service(dp, 'load_map', LoadMapRequest, LoadMapResponse)
    reset = Service(dp, 'reset_map', TriggerRequest, TriggerResponse)
    ray = Service(dp, 'raytrace', RaytraceRequest, RaytraceResponse)
    saved = str(Path(out, 'saved.map'))
    r = save.call(SaveMapRequest(saved))
    result['save'] = [r.success, r.message]
    r = save.call(SaveMapRequest('/nonexistent-dir/x.map'))
    result['save_bad'] = [r.success, r.message]
    rays = []
    for o, d in json.loads(os.environ.get('VOXMAP_PEER_RAYS', '[]')):
        r = ray.call(RaytraceRequest(Point(*o), Vector3(*d), 8.0))
        rays.append([r.success, r.hit, [r.end_point.x, r.end_point.y, r.end_point.z], r.message])
    r = ray.call(RaytraceRequest(Point(0, 0, 0), Vector3(0, 0, 0), 1.0))
    rays.append([r.success, r.hit, [r.end_point.x, r.end_point.y, r.end_point.z], r.message])
    result['rays'] = rays
    r = reset.call(TriggerRequest(0))
    result['reset'] = [r.success, r.message]
    empty = take_maps(readers, last_ns, want=lambda occ: occ.width == 0)
    result['after_reset_occupied'] = empty[0].width
    r = load.call(LoadMapRequest(saved))
    result['load'] = [r.success, r.message]
    loaded = take_maps(readers, last_ns, want=lambda occ: occ.width > 0)
    result['loaded'] = write_maps(out, loaded, 'loaded')
    Path(out, 'publish.json').write_text(json.dumps(result, indent=1))


def listen(out):
    dp = DomainParticipant(DOMAIN)
    readers = map_readers(dp)
    want = json.loads(Path(out, 'publish.json').read_text())['last_ns']
    # The map after the load: all three versions since the last frame (the map, the
    # reset one, the loaded one) carry that frame's stamp, and a late reader may see an
    # older one first.
    maps = take_maps(readers, want, timeout=30.0, want=lambda occ: occ.width > 0)
    Path(out, 'listen.json').write_text(json.dumps(write_maps(out, maps, 'late'), indent=1))


def cyclone_reset(out):
    dp = DomainParticipant(DOMAIN)
    reset = Service(dp, 'reset_map', CycloneTriggerRequest, CycloneTriggerResponse)
    guid = [1, 2, 3, 4, 5, 6, 7, 8]
    r = reset.call(CycloneTriggerRequest(guid, 0, 77, 0))
    Path(out, 'cyclone.json').write_text(json.dumps({
        'guid': list(r.client_guid_low), 'sequence': [r.sequence_high, r.sequence_low],
        'success': r.success, 'message': r.message}))


if __name__ == '__main__':
    if sys.argv[1:2] == ['publish'] and len(sys.argv) == 4:
        publish(sys.argv[2], sys.argv[3])
    elif sys.argv[1:2] == ['listen'] and len(sys.argv) == 3:
        listen(sys.argv[2])
    elif sys.argv[1:2] == ['cyclone-reset'] and len(sys.argv) == 3:
        cyclone_reset(sys.argv[2])
    else:
        raise SystemExit(__doc__)
