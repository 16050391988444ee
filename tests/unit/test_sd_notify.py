"""The sd_notify protocol against a real AF_UNIX datagram socket, as systemd's end would read it."""

import logging
import os
import threading

import pytest

from appliance.live.sd_notify import NOTIFY_VARIABLES, ServiceNotifier, child_environment
from tests.system.notify_harness import NotifySocket

RECEIVE_TIMEOUT_S = 5.0
NOTHING_TIMEOUT_S = 0.05


class FakeClock:
    def __init__(self) -> None:
        self.now_s = 100.0

    def __call__(self) -> float:
        return self.now_s


@pytest.fixture(params=["path", "abstract"])
def receiver(request):
    with NotifySocket(abstract=request.param == "abstract") as notify_socket:
        yield notify_socket


def received_texts(receiver: NotifySocket) -> list[str]:
    texts = []
    while (notification := receiver.receive(NOTHING_TIMEOUT_S)) is not None:
        texts.append(notification.text)
    return texts


def test_every_notification_arrives_with_the_sender_pid(receiver):
    notifier = ServiceNotifier({"NOTIFY_SOCKET": receiver.name, "WATCHDOG_USEC": "2000000"})
    assert notifier.enabled and notifier.watchdog_interval_s == 2.0
    assert notifier.ready()
    assert notifier.status("measuring, 25.0 fps")
    assert notifier.watchdog()
    assert notifier.stopping()
    texts = []
    for _ in range(4):
        notification = receiver.receive(RECEIVE_TIMEOUT_S)
        assert notification is not None
        assert notification.pid == os.getpid()
        texts.append(notification.text)
    assert texts == ["READY=1", "STATUS=measuring, 25.0 fps", "WATCHDOG=1", "STOPPING=1"]
    assert notifier.lost_notifications == 0


def test_status_goes_with_ready_and_stopping_in_one_datagram_on_one_line(receiver):
    notifier = ServiceNotifier({"NOTIFY_SOCKET": receiver.name})
    notifier.ready("waiting for\nthe start command")
    notifier.stopping("closing the recording")
    notifier.extend_timeout(12.5)
    assert received_texts(receiver) == [
        "READY=1\nSTATUS=waiting for the start command",
        "STOPPING=1\nSTATUS=closing the recording",
        "EXTEND_TIMEOUT_USEC=12500000",
    ]


def test_watchdog_pings_at_most_once_per_half_interval(receiver):
    clock = FakeClock()
    notifier = ServiceNotifier(
        {"NOTIFY_SOCKET": receiver.name, "WATCHDOG_USEC": "1000000"}, clock=clock
    )
    sent_at = []
    for step in range(300):
        clock.now_s = 100.0 + step * 0.01
        if notifier.watchdog():
            sent_at.append(round(clock.now_s - 100.0, 2))
    assert sent_at == [0.0, 0.5, 1.0, 1.5, 2.0, 2.5]
    assert received_texts(receiver) == ["WATCHDOG=1"] * 6


def test_a_frame_slower_than_half_the_interval_pings_on_every_frame(receiver):
    clock = FakeClock()
    notifier = ServiceNotifier(
        {"NOTIFY_SOCKET": receiver.name, "WATCHDOG_USEC": "1000000"}, clock=clock
    )
    results = []
    for step in range(4):
        clock.now_s = 100.0 + step * 0.6
        results.append(notifier.watchdog())
    assert results == [True, True, True, True]


@pytest.mark.parametrize(
    ("environment", "interval_s"),
    [
        ({}, None),
        ({"WATCHDOG_USEC": ""}, None),
        ({"WATCHDOG_USEC": "0"}, None),
        ({"WATCHDOG_USEC": "ten"}, None),
        ({"WATCHDOG_USEC": "500000"}, 0.5),
        ({"WATCHDOG_USEC": "500000", "WATCHDOG_PID": "own"}, 0.5),
        ({"WATCHDOG_USEC": "500000", "WATCHDOG_PID": "other"}, None),
        ({"WATCHDOG_USEC": "500000", "WATCHDOG_PID": "not a pid"}, None),
    ],
)
def test_the_watchdog_is_this_process_s_only_as_sd_watchdog_enabled_says(
    receiver, environment, interval_s
):
    pids = {"own": str(os.getpid()), "other": str(os.getpid() + 1)}
    environ = {key: pids.get(value, value) for key, value in environment.items()}
    notifier = ServiceNotifier({"NOTIFY_SOCKET": receiver.name, **environ})
    assert notifier.watchdog_interval_s == interval_s
    assert notifier.watchdog() is (interval_s is not None)
    assert received_texts(receiver) == (["WATCHDOG=1"] if interval_s else [])


def test_without_notify_socket_everything_is_a_no_op():
    notifier = ServiceNotifier({"WATCHDOG_USEC": "1000000"})
    assert not notifier.enabled
    assert notifier.watchdog_interval_s is None
    results = [
        notifier.ready("up"),
        notifier.status("x"),
        notifier.watchdog(),
        notifier.extend_timeout(5),
        notifier.stopping(),
    ]
    assert results == [False] * 5
    assert notifier.lost_notifications == 0
    notifier.close()


def test_an_unusable_socket_name_is_logged_and_ignored(caplog):
    with caplog.at_level(logging.WARNING, logger="appliance.live.sd_notify"):
        notifier = ServiceNotifier({"NOTIFY_SOCKET": "vsock:2:1234"})
    assert not notifier.enabled and notifier.ready() is False
    assert "vsock:2:1234" in caplog.text


def test_the_process_environment_is_read_by_default_and_left_as_it_was(receiver, monkeypatch):
    monkeypatch.setenv("NOTIFY_SOCKET", receiver.name)
    monkeypatch.setenv("WATCHDOG_USEC", "3000000")
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    notifier = ServiceNotifier()
    assert notifier.ready() and notifier.watchdog_interval_s == 3.0
    assert os.environ["NOTIFY_SOCKET"] == receiver.name
    assert received_texts(receiver) == ["READY=1"]
    stripped = child_environment()
    assert not set(NOTIFY_VARIABLES) & set(stripped)
    assert stripped["PATH"] == os.environ["PATH"]


def test_a_lost_listener_is_logged_once_and_never_raises(tmp_path, caplog):
    name = str(tmp_path / "notify")
    NotifySocket(name).close()
    notifier = ServiceNotifier({"NOTIFY_SOCKET": name, "WATCHDOG_USEC": "1"})
    with caplog.at_level(logging.INFO, logger="appliance.live.sd_notify"):
        assert notifier.ready() is False
        assert notifier.status("still here") is False
        assert notifier.watchdog() is False
        assert notifier.stopping() is False
        warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
        assert len(warnings) == 1 and name in warnings[0].getMessage()
        assert notifier.lost_notifications == 4
        with NotifySocket(name) as back:
            assert notifier.status("reconnected") is True
            assert back.receive(RECEIVE_TIMEOUT_S).text == "STATUS=reconnected"
    assert "again (4 notifications lost so far)" in caplog.records[-1].getMessage()


def test_a_full_queue_drops_notifications_instead_of_blocking(receiver, caplog):
    notifier = ServiceNotifier({"NOTIFY_SOCKET": receiver.name})
    outcomes: list[bool] = []

    def flood() -> None:
        outcomes.extend(notifier.status(f"frame {i}") for i in range(5000))

    sender = threading.Thread(target=flood, daemon=True)
    with caplog.at_level(logging.WARNING, logger="appliance.live.sd_notify"):
        sender.start()
        sender.join(timeout=60)
    assert not sender.is_alive(), "a notification blocked on a full socket queue"
    assert False in outcomes and notifier.lost_notifications == outcomes.count(False)
    assert len([r for r in caplog.records if r.levelno == logging.WARNING]) == 1


def test_threads_share_one_notifier_without_mixing_datagrams_or_losing_count(receiver):
    notifier = ServiceNotifier({"NOTIFY_SOCKET": receiver.name, "WATCHDOG_USEC": "3600000000"})
    threads_n, messages_n = 6, 40
    received: list[str] = []
    sent: list[str] = []
    not_sent: list[str] = []
    done = threading.Event()

    def read() -> None:
        while True:
            notification = receiver.receive(0.2)
            if notification is not None:
                received.append(notification.text)
            elif done.is_set():
                return

    def send(thread: int) -> None:
        for i in range(messages_n):
            text = f"thread {thread} message {i}"
            (sent if notifier.status(text) else not_sent).append(f"STATUS={text}")
            notifier.watchdog()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    senders = [threading.Thread(target=send, args=(t,), daemon=True) for t in range(threads_n)]
    for sender in senders:
        sender.start()
    for sender in senders:
        sender.join(timeout=60)
    done.set()
    reader.join(timeout=60)
    assert not reader.is_alive() and not any(sender.is_alive() for sender in senders)
    assert len(sent) + len(not_sent) == threads_n * messages_n
    assert sorted(text for text in received if text != "WATCHDOG=1") == sorted(sent)
    assert received.count("WATCHDOG=1") <= 1
    assert len(not_sent) <= notifier.lost_notifications <= len(not_sent) + 1


def test_a_closed_notifier_drops_silently(receiver):
    with ServiceNotifier({"NOTIFY_SOCKET": receiver.name, "WATCHDOG_USEC": "1000"}) as notifier:
        assert notifier.ready()
    assert not notifier.enabled
    assert [notifier.status("late"), notifier.watchdog(), notifier.stopping()] == [False] * 3
    assert notifier.lost_notifications == 0
    assert received_texts(receiver) == ["READY=1"]
