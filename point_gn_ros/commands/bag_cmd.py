"""`point_gn bag write|info` and `point_gn replay`: ground-truth bags and their replay."""

from __future__ import annotations

import argparse
import json
import sys

from point_gn_ros.commands.common import add_dataset_args

DEFAULT_TOPIC = '/segmented_objects'   # = point_gn_ros.bag.DEFAULT_TOPIC (kept import-free)


def register(sub: argparse._SubParsersAction) -> None:
    bag = sub.add_parser('bag', help='write a dataset split as a ground-truth rosbag2 bag')
    actions = bag.add_subparsers(dest='bag_action', required=True, metavar='ACTION')

    w = actions.add_parser(
        'write', help='dataset split -> bag of PointCloud2 objects with gt_label',
        description='Write a dataset split as sensor_msgs/PointCloud2 messages (x, y, z, '
                    'gt_label [, segment]) plus the class names on /point_gn/class_names.')
    add_dataset_args(w, 'test')
    w.add_argument('-o', '--output', required=True, metavar='BAG',
                   help='bag directory to create (must not exist)')
    w.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap',
                   help='rosbag2 storage plugin (default mcap)')
    w.add_argument('--rate', type=float, default=10.0, metavar='HZ',
                   help='recorded message rate (header stamps and bag times; default 10)')
    w.add_argument('--objects-per-message', type=int, default=1, metavar='N',
                   help='objects per message; > 1 adds an INT32 segment field (default 1)')
    w.add_argument('--topic', default=DEFAULT_TOPIC, help=f'cloud topic (default {DEFAULT_TOPIC})')
    w.add_argument('--frame-id', default='sensor', help="header frame_id (default 'sensor')")
    w.add_argument('--limit', type=int, default=None, metavar='N',
                   help='write only the first N objects')
    w.add_argument('--sensor-frame', action='store_true',
                   help='place objects in a sensor frame: 0.3-2 m in size, yawed, 2-8 m ahead')
    w.add_argument('--max-yaw', type=float, default=180.0, metavar='DEG',
                   help='--sensor-frame: yaw about z drawn from [-DEG, DEG] (default 180)')
    w.add_argument('--noise', type=float, default=0.0, metavar='SIGMA_M',
                   help='Gaussian noise sigma (metres with --sensor-frame; default 0)')
    w.add_argument('--dropout', type=float, default=0.0, metavar='P',
                   help='drop each point with probability P (default 0)')
    w.add_argument('--partial', type=float, default=1.0, metavar='SHARE',
                   help='partial view: keep SHARE of the points by a random plane cut')
    w.add_argument('--single-view', action='store_true',
                   help='a simulated single-view scan of each object (hidden point removal, '
                        'sensor noise: the default protocol of core/views.py); with '
                        '--sensor-frame the scanned side faces the sensor')
    w.add_argument('--seed', type=int, default=0, help='seed of the realism transforms')
    w.set_defaults(func=_write)

    i = actions.add_parser('info', help='check a bag and summarise its ground truth')
    i.add_argument('bag', metavar='BAG', help='bag directory (or .mcap / .db3 file)')
    i.add_argument('--topic', default=None, help='cloud topic (default: auto)')
    i.set_defaults(func=_info)

    pl = actions.add_parser(
        'play', help="publish a bag's topics at the recorded rate (no ros2 bag needed)",
        description="Publish a rosbag2 bag's messages (raw, as recorded) on their topics, "
                    'paced by the recorded times; ROS_DOMAIN_ID from the environment.')
    pl.add_argument('bag', metavar='BAG', help='bag directory (or .mcap / .db3 file)')
    pl.add_argument('--rate', type=float, default=1.0, metavar='R',
                    help='R x the recorded rate (default 1)')
    pl.add_argument('--loop', action='store_true', help='start again at the end (Ctrl-C stops)')
    pl.add_argument('--topics', nargs='+', default=None, metavar='TOPIC',
                    help='only these topics (default: all)')
    pl.add_argument('--wait-for-subscribers', type=float, default=0.0, metavar='S',
                    help='before playing, wait up to S s until every topic has a subscriber '
                         '(default 0: a 1 s pause only)')
    pl.set_defaults(func=_play)

    r = sub.add_parser(
        'replay', help='replay a ground-truth bag through the classifier node and report',
        description="Publish the bag's clouds to the running classifier node (or only listen, "
                    'or classify offline), match its answers by header stamp and report '
                    'accuracy, delivery and latency.')
    r.add_argument('bag', metavar='BAG',
                   help='any rosbag2 bag (mcap or sqlite3) of PointCloud2 messages; a bag '
                        'written by `point_gn bag write` (ground truth) gets the accuracy '
                        'report')
    how = r.add_mutually_exclusive_group()
    how.add_argument('--offline', action='store_true',
                     help='no ROS graph: classify with the core library (same report), as '
                          'a node at its defaults')
    r.add_argument('--no-units', action='store_true',
                   help='with --offline: the clouds are not in metres (e.g. unit-sphere '
                        'ModelNet40): no size evidence, as the node with metric_size false')
    how.add_argument('--listen-only', action='store_true',
                     help='do not publish (play the bag with ros2 bag play); listen and match')
    how.add_argument('--lockstep', action='store_true',
                     help='send the next message only when the previous one is answered '
                          '(or --timeout passes)')
    how.add_argument('--rate', type=float, default=1.0, metavar='R',
                   help='publish at R x the recorded rate (default 1)')
    r.add_argument('--topic', action='append', default=None, metavar='TOPIC',
                   help='cloud topic in the bag, repeatable (default: every PointCloud2 topic; '
                        'a ground-truth bag: its cloud topic)')
    r.add_argument('--csv', default=None, metavar='ANSWERS.csv',
                   help='bag without ground truth: one row per object (stamp, topic, frame, '
                        'segment, label, score, top-k, latency)')
    r.add_argument('--output-bag', default=None, metavar='OUT_BAG',
                   help='bag without ground truth: write the input clouds and the answers '
                        '(~/classifications PointCloud2; live, with vision_msgs: also '
                        '~/detections Detection3DArray) to a new bag')
    r.add_argument('--segment-field', default='', metavar='FIELD',
                   help='offline: the node parameter segment_field (default none: a message '
                        'is one object)')
    r.add_argument('--up-axis', default='auto',
                   choices=('auto', 'z', '-z', 'y', '-y', 'x', '-x'),
                   help='offline: the node parameter up_axis (default auto)')
    r.add_argument('--node-name', default=None, metavar='NAME',
                   help='classifier node name (answers on /NAME/classifications; default: the '
                        'node subscribed to the cloud topic)')
    r.add_argument('--timeout', type=float, default=10.0, metavar='S',
                   help='lockstep: wait per message; otherwise: give up after S s without an '
                        'answer (default 10)')
    r.add_argument('--discovery-timeout', type=float, default=60.0, metavar='S',
                   help='wait for the node (listen-only: for the first answer; default 60)')
    r.add_argument('--best-effort', action='store_true',
                   help='publish best-effort (default reliable)')
    r.add_argument('--bank', default=None, help='offline: bank file (default: the shipped bank)')
    r.add_argument('--device', default='cpu', help='offline: torch device (default cpu)')
    r.add_argument('--unknown-threshold', type=float, default=None,
                   help='offline: open-set threshold, as the node parameter')
    r.add_argument('--min-points', type=int, default=16,
                   help='offline: skip objects with fewer points, as the node (default 16)')
    r.add_argument('--min-answered', type=float, default=0.0, metavar='SHARE',
                   help='exit 1 unless at least this share (0-1) of the sent messages is '
                        'answered (default 0: exit 1 only when nothing is); duplicate '
                        'answers also exit 1')
    r.add_argument('--json', default=None, metavar='REPORT.json',
                   help='write the JSON report (without ground truth: every answer)')
    r.add_argument('--markdown', default=None, metavar='REPORT.md',
                   help='write the Markdown report')
    r.add_argument('--png', default=None, metavar='PREFIX',
                   help='write PREFIX_confusion.png and PREFIX_latency.png')
    r.add_argument('--quiet', action='store_true', help='no report on stdout')
    r.set_defaults(func=_replay)


def _write(args: argparse.Namespace) -> int:
    from point_gn_ros.bag.realism import Realism
    from point_gn_ros.bag.writer import WriteOptions, write_bag
    from point_gn_ros.commands.common import open_dataset_from_args

    opts = WriteOptions(
        storage=args.storage, rate_hz=args.rate, objects_per_message=args.objects_per_message,
        topic=args.topic, limit=args.limit, frame_id=args.frame_id, seed=args.seed,
        realism=Realism(args.sensor_frame, args.noise, args.dropout, args.partial,
                        args.max_yaw, args.single_view))
    opts.check()   # before the (slow) dataset opens
    ds = open_dataset_from_args(args)
    summary = write_bag(ds, args.output, opts, source=f'{ds.path} [{ds.split}]',
                        progress=sys.stderr.isatty())
    print(summary.line())
    return 0


def _info(args: argparse.Namespace) -> int:
    from point_gn_ros.bag.errors import NoGroundTruthError
    from point_gn_ros.bag.reader import read_bag

    try:
        contents = read_bag(args.bag, args.topic)
    except NoGroundTruthError as exc:
        from collections import Counter

        from point_gn_ros.bag.any_bag import read_clouds
        bag = read_clouds(args.bag, [args.topic] if args.topic else None)
        per_topic = Counter(m.topic for m in bag.messages)
        print(f'{bag.path} ({bag.storage}): no ground truth ({exc}); PointCloud2 messages: '
              + ', '.join(f'{t} {n}' for t, n in sorted(per_topic.items())))
        return 0
    print(contents.summary())
    for key, value in sorted(contents.custom.items()):
        if not key.endswith('class_names'):
            print(f'  {key}: {value}')
    return 0


def _play(args: argparse.Namespace) -> int:
    from point_gn_ros.bag.play import play

    sent = play(args.bag, args.topics, args.rate, args.loop,
                log=lambda text: print(f'[bag play] {text}', file=sys.stderr, flush=True),
                wait_subscribers_s=args.wait_for_subscribers)
    print(f'published {sent} message(s)')
    return 0


def _replay(args: argparse.Namespace) -> int:
    from point_gn_ros.bag.reader import read_bag
    from point_gn_ros.bag.report import build_report, format_markdown, write_outputs

    if not 0.0 <= args.min_answered <= 1.0:
        from point_gn_ros.bag.errors import ReplayError
        raise ReplayError(f'--min-answered must be a share in [0, 1], got {args.min_answered:g}')
    from point_gn_ros.bag.errors import NoGroundTruthError

    topics = args.topic or []
    try:
        if len(topics) > 1:
            raise NoGroundTruthError('several topics: answers only')
        contents = read_bag(args.bag, topics[0] if topics else None,
                            keep_clouds=args.offline)
    except NoGroundTruthError:
        return _replay_answers(args)
    if args.csv or args.output_bag:
        print('point_gn: replay: --csv and --output-bag are for bags without ground truth; '
              'ignored', file=sys.stderr)
    if args.offline:
        from point_gn_ros.bag.offline import run_offline
        result = run_offline(contents, args.bank, args.device, args.unknown_threshold,
                             args.min_points, progress=sys.stderr.isatty(),
                             metric_size=not args.no_units)
    else:
        from point_gn_ros.bag.replay import ReplayOptions, run_replay
        mode = 'listen-only' if args.listen_only else 'lockstep' if args.lockstep else 'rate'
        result = run_replay(contents, ReplayOptions(
            mode=mode, rate=args.rate, node_name=args.node_name, timeout=args.timeout,
            discovery_timeout=args.discovery_timeout, reliable=not args.best_effort))
    report = build_report(contents, result)
    write_outputs(report, contents.class_names, json_path=args.json,
                  markdown_path=args.markdown, png_prefix=args.png)
    if not args.quiet:
        print(format_markdown(report, contents.class_names))
    elif not (args.json or args.markdown):
        print(json.dumps({k: report[k] for k in ('accuracy', 'sent', 'answered', 'latency_ms')}))
    problems = replay_problems(report, args.min_answered)
    for problem in problems:
        print(f'point_gn: replay: {problem}', file=sys.stderr)
    return 1 if problems else 0


def _replay_answers(args: argparse.Namespace) -> int:
    """A bag without ground truth: classify every cloud, write and summarise the answers."""
    from point_gn_ros.bag.any_bag import (CLASSIFICATIONS_TOPIC, classify_live,
                                          classify_offline, format_summary, read_clouds,
                                          summarise, write_answers, write_output_bag)

    bag = read_clouds(args.bag, args.topic)
    header: dict = {'bag': str(bag.path), 'storage': bag.storage, 'topics': bag.topics}
    if args.offline:
        answers, names, rejected = classify_offline(
            bag, args.bank, args.device, args.unknown_threshold, args.min_points,
            args.segment_field, up_axis=args.up_axis, metric_size=not args.no_units)
        answered = len({a.message for a in answers})
        header |= {'mode': 'offline', 'rejected': rejected}
        answer_msgs = _offline_answer_msgs(bag, answers, names) if args.output_bag else []
        answers_topic = CLASSIFICATIONS_TOPIC
        detections = []
    else:
        if args.listen_only or args.lockstep:
            print('point_gn: replay: a bag without ground truth is sent at --rate; '
                  '--listen-only / --lockstep apply to ground-truth bags', file=sys.stderr)
        answers, names, info = classify_live(
            bag, args.node_name, args.rate, args.timeout, args.discovery_timeout,
            log=lambda text: print(f'[replay] {text}', file=sys.stderr, flush=True))
        answered = info['answered']
        header |= {'mode': 'live', 'node': info['node'], 'sent': info['sent'],
                   'unmatched_answers': info['unmatched_answers']}
        from rclpy.serialization import serialize_message
        answer_msgs = [(serialize_message(m), log_ns) for m, log_ns in info['answer_messages']]
        answers_topic = (info['node'] or '/point_gn') + '/classifications'
        detections = info['detections']
    summary = summarise(answers, len(bag.messages), answered)
    header |= {'class_names': names, 'summary': summary}
    write_answers(answers, header, json_path=args.json, csv_path=args.csv)
    if args.output_bag:
        write_output_bag(bag, args.output_bag, answer_msgs, answers_topic,
                         'sqlite3' if bag.storage == 'sqlite3' else 'mcap', detections,
                         answers_topic.rsplit('/', 1)[0] + '/detections')
    if not args.quiet:
        print(format_summary(summary))
    if bag.messages and answered == 0:
        print(f'point_gn: replay: answered 0 of {len(bag.messages)} message(s)', file=sys.stderr)
        return 1
    return 0


def _offline_answer_msgs(bag: object, answers: list, names: list[str]) -> list:
    """Offline answers as ~/classifications CDR, logged at their input message's time."""
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Header
    from builtin_interfaces.msg import Time

    import numpy as np

    from point_gn_ros.pointcloud2 import make_classifications

    by_msg: dict[int, list] = {}
    for a in answers:
        by_msg.setdefault(a.message, []).append(a)
    out = []
    for m in bag.messages:
        rows = by_msg.get(m.index)
        if not rows:
            continue
        index = {n: i for i, n in enumerate(names)}
        header = Header(frame_id=m.frame_id, stamp=Time(sec=m.stamp_ns // 1_000_000_000,
                                                        nanosec=m.stamp_ns % 1_000_000_000))
        msg = make_classifications(
            header, np.array([a.centroid for a in rows]), [a.class_id for a in rows],
            [a.score for a in rows], [[index.get(n, -1) for n, _ in a.topk] for a in rows],
            [[s for _, s in a.topk] for a in rows], np.array([a.segment for a in rows]),
            bag.topics.index(m.topic))
        out.append((serialize_message(msg), m.log_ns))
    return out


def replay_problems(report: dict, min_answered: float = 0.0) -> list[str]:
    """Why a replay failed: too little answered, or answered twice; [] when it passed."""
    problems = []
    sent, answered = report['sent'], report['answered']
    if sent and (answered == 0 or answered < min_answered * sent):
        problems.append(f'answered {answered} of {sent} message(s)'
                        + (f', less than --min-answered {min_answered:g}' if answered else
                           ': is the node classifying (see its log and /diagnostics)?'))
    dupes = report.get('info', {}).get('duplicate_answers', 0)
    if dupes:
        problems.append(f'{dupes} duplicate answer(s): more than one node answers '
                        f'{report["topic"]} (nodes: '
                        f'{", ".join(report["info"].get("classifier_nodes", [])) or "?"})')
    return problems
