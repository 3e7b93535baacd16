"""``telerig say "PHRASE"`` and ``telerig voice``: operator commands through the voice grammar.

``say`` sends one typed phrase (the same grammar as speech); ``voice`` recognizes WAV files or the
microphone (``arecord``) and sends what it hears. Both log in to the running rig's broker as
``telerig session`` does, print the reply in one line and speak it with ``--speak``.
"""

from __future__ import annotations

import argparse
import secrets
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from telerig.cli.bus_options import add_bus_options, bus_connection
from telerig.errors import BusError, SessionError

if TYPE_CHECKING:
    from telerig.bus.mqtt import MqttBus
    from telerig.voice.dispatch import Dispatcher, Reply

__all__ = ["add_arguments"]


def add_arguments(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``telerig say`` and ``telerig voice``."""
    say = sub.add_parser(
        "say",
        help="one operator command in words, e.g. telerig say navigation (the voice command grammar)",
        description="Send one phrase of the voice command grammar to a running rig. A critical phrase "
        "(release emergency stop) is only staged: say 'robot please execute' next, within 10 s, in the "
        "same call: telerig say 'release emergency stop' 'robot please execute'.",
    )
    say.add_argument("phrases", nargs="+", help="phrases, handled in order")
    voice = sub.add_parser(
        "voice",
        help="voice commands: recognize WAV files or the microphone and send what is heard",
        description="Offline speech recognition (pocketsphinx) of the command grammar.",
    )
    voice.add_argument("--wav", type=Path, nargs="*", default=[], help="WAV files, one utterance each")
    voice.add_argument("--mic", action="store_true", help="listen to the microphone (arecord) until Ctrl-C")
    voice.add_argument("--seconds", type=float, default=3.0, help="microphone: seconds per utterance")
    for p in (say, voice):
        p.add_argument("--rig", default="demo", help="rig name, file or shipped rig (default: demo)")
        p.add_argument("--robot", default=None, help="robot for aid commands and e-stops (default: the one)")
        p.add_argument("--speak", action="store_true", help="say the replies aloud (espeak-ng)")
        add_bus_options(p)
    say.set_defaults(handler=_cmd_say)
    voice.set_defaults(handler=_cmd_voice)


def _connect(args: argparse.Namespace, source: str) -> tuple[MqttBus, Dispatcher]:
    from telerig.bus.mqtt import MqttBus
    from telerig.config import load_rig
    from telerig.voice.feedback import Speaker
    from telerig.voice.node import connect_dispatcher

    rig = load_rig(args.rig)
    url, tls = bus_connection(args, rig)
    try:
        bus = MqttBus(url, client_id=f"{source}-voice-{secrets.token_hex(3)}", tls=tls).connect()
    except BusError as exc:
        raise SessionError(f"cannot reach the rig's broker: {exc}; is `telerig run` running?") from None
    speaker = Speaker() if args.speak else None
    dispatcher = connect_dispatcher(
        bus, rig.name, robot=args.robot, source=source, say=None if speaker is None else speaker.say
    )
    return bus, dispatcher


def _print(reply: Reply) -> None:
    stream = sys.stdout if reply.status != "rejected" else sys.stderr
    print(f"{reply.status}: {reply.say}" + (f" ({reply.heard!r})" if reply.heard else ""), file=stream)


def _cmd_say(args: argparse.Namespace) -> int:
    bus, dispatcher = _connect(args, "cli")
    with bus:
        replies = [dispatcher.handle(p, source="cli") for p in args.phrases]
        for reply in replies:
            _print(reply)
        time.sleep(0.2)  # let the QoS 1 publishes leave before disconnecting
    return 1 if any(r.status == "rejected" for r in replies) else 0


def _cmd_voice(args: argparse.Namespace) -> int:
    from telerig.voice.node import listen, microphone
    from telerig.voice.recognizer import Recognizer

    if not args.wav and not args.mic:
        print("error: give --wav FILE... or --mic", file=sys.stderr)
        return 2
    recognizer = Recognizer()
    bus, dispatcher = _connect(args, "voice")
    with bus:
        audio = microphone(args.seconds) if args.mic else iter(args.wav)
        rejected = 0
        try:
            for utterance in audio:
                for reply in listen(dispatcher, recognizer, [utterance]):
                    _print(reply)
                    rejected += reply.status == "rejected"
        except KeyboardInterrupt:
            pass
        time.sleep(0.2)
    return 1 if rejected else 0
