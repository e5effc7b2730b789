#!/usr/bin/env python3
"""The web console in a real browser (docs/console.md, "Tests").

Starts placedb-server (console on a free loopback port, found with `placedb console`), ingests
RTAB-Map frames with the placedb CLI from two agents, then drives Debian's headless chromium
over the DevTools protocol (python3-websocket) through every page:

  maps    the map's row shows its places;
  places  place cards with their thumbnails drawn (the map keeps them);
  query   a frame uploaded with DOM.setFileInputFiles: the top match is that frame's place,
          verified, with its inlier correspondences drawn;
  live    agents and latest places, refreshed without reloading;
  dynamics  a map of frames with person and car boxes (sent over gRPC with messages generated
          from proto/placedb.proto by protoc: the CLI sends no boxes): its first card within
          1 s (measured, reported), class totals, hours, the places ranked by class.

Screenshots go to PLACEDB_CONSOLE_SCREENSHOTS (the build dir's console-screenshots/). A page
error (a JavaScript exception) fails the test. Without chromium the test fails with a clear
message; PLACEDB_SKIP_BROWSER_TEST=1 turns that into a skip (exit 77) for local runs only.

Environment: PLACEDB_SERVER_BINARY, PLACEDB_CLI_BINARY, PLACEDB_DEFAULT_VOCABULARY,
PLACEDB_SHARED_DIR, PLACEDB_CONSOLE_SCREENSHOTS; PLACEDB_CHROMIUM (default: chromium on PATH).
"""

import base64
import json
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request

SKIP = 77
FRAMES = 40      # RTAB-Map loop frames 1..40 make the map
# The RTAB-Map loop's frames are 512x384: a plausible pinhole camera for the office map.
OFFICE_CAMERA = "410,410,256,192"
QUERY_FRAME = 23  # a stored frame: its own place must be the top match


def fail(message):
    print("FAIL: " + message, file=sys.stderr)
    sys.exit(1)


def env(name):
    value = os.environ.get(name)
    if not value:
        fail(name + " is not set (ctest sets it: tests/CMakeLists.txt, console_browser_test)")
    return value


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(what, predicate, timeout=60.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.1)
    fail("timed out waiting for " + what)


class DevTools:
    """One page target of chromium's DevTools protocol over its websocket."""

    def __init__(self, url):
        import websocket  # python3-websocket

        self.ws = websocket.create_connection(url, timeout=120, suppress_origin=True)
        self.next_id = 0
        self.errors = []

    def call(self, method, **params):
        self.next_id += 1
        self.ws.send(json.dumps({"id": self.next_id, "method": method, "params": params}))
        while True:
            message = json.loads(self.ws.recv())
            if message.get("method") == "Runtime.exceptionThrown":
                details = message["params"]["exceptionDetails"]
                self.errors.append(details.get("exception", {}).get("description")
                                   or details.get("text"))
            if message.get("id") == self.next_id:
                if "error" in message:
                    fail(method + ": " + json.dumps(message["error"]))
                return message["result"]

    def evaluate(self, expression):
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True,
                           awaitPromise=True)
        if "exceptionDetails" in result:
            fail("evaluating " + expression + ": " + json.dumps(result["exceptionDetails"]))
        return result["result"].get("value")

    def show(self, hash_route):
        """Switches the console to a view and waits until it has loaded."""
        self.evaluate("document.getElementById('view').dataset.ready = 'stale';"
                      "location.hash = %s;" % json.dumps(hash_route))
        wait_for(hash_route + " to load", lambda: self.evaluate(
            "document.getElementById('view').dataset.ready === 'yes'"))
        status = self.evaluate(
            "(() => { const s = document.getElementById('status');"
            " return s.classList.contains('hidden') || s.classList.contains('info') ? '' :"
            " s.textContent; })()")
        if status:
            fail(hash_route + " shows an error: " + status)
        if self.errors:
            fail(hash_route + ": page error: " + "; ".join(self.errors))

    def screenshot(self, path):
        # 1280x900 at 0.625: 800x562 PNGs, small enough to keep in docs/console/.
        shot = self.call("Page.captureScreenshot", format="png",
                         clip={"x": 0, "y": 0, "width": 1280, "height": 900, "scale": 0.625})
        with open(path, "wb") as out:
            out.write(base64.b64decode(shot["data"]))
        print("screenshot " + path)


# Watches the places page from the moment it is installed: when the first cards appear (how
# many, how many drawn), when every card is drawn, and how many GetPlace calls run at once.
# Counts the page's GetPlace fetches in flight (probe.inFlight, probe.maxInFlight): the probes
# below check that cards are fetched in parallel.
COUNT_GETPLACE_FETCHES = """  const fetch = window.fetch;
  window.fetch = (url, options) => {
    if (!String(url).endsWith('/GetPlace')) return fetch(url, options);
    probe.inFlight++;
    probe.maxInFlight = Math.max(probe.maxInFlight, probe.inFlight);
    return fetch(url, options).finally(() => probe.inFlight--);
  };
"""

PLACES_PROBE = """(() => {
  const probe = { firstCards: null, firstMs: null, drawnAtFirst: null, allDrawnMs: null,
                  maxInFlight: 0, inFlight: 0 };
  const start = performance.now();
""" + COUNT_GETPLACE_FETCHES + """  const observer = new MutationObserver(() => {
    const cards = document.querySelectorAll('#places .place-card');
    const drawn = document.querySelectorAll(
        '#places .place-card canvas[data-thumbnail="yes"], #places .place-card canvas[data-thumbnail="no"]');
    if (cards.length && probe.firstCards === null) {
      probe.firstCards = cards.length;
      probe.firstMs = performance.now() - start;
      probe.drawnAtFirst = drawn.length;
    }
    if (cards.length && drawn.length === cards.length && probe.allDrawnMs === null &&
        document.getElementById('places').dataset.loaded === 'yes') {
      probe.allDrawnMs = performance.now() - start;
    }
  });
  observer.observe(document.getElementById('view'), { childList: true, subtree: true,
                                                      attributes: true });
  probe.stop = () => { observer.disconnect(); window.fetch = fetch; };
  window.placedbProbe = probe;
})()"""


def follow_live(devtools, url, placedb, frames_dir):
    """Two agents ingest at 4 frames/s each while the live page is open: every place stored must
    show on it (as the newest) within a generous deadline; the delays are reported."""
    live_frames = tempfile.mkdtemp(prefix="placedb-console-live-")
    try:
        for i in range(41, 85):
            os.symlink(os.path.join(frames_dir, "%d.jpg" % i), os.path.join(live_frames, "%d.jpg" % i))
        newest_in_map = lambda: int((console_api(url, "ListPlaces", {"map": "office", "limit": 1})
                                     .get("places") or [{"place_id": 0}])[0]["place_id"])
        before = newest_in_map()
        # Every GetPlace the live page makes from here, by place id, each answered 1 s late (a
        # server as loaded as issue 33's, where one took about that): new places must still
        # show at once, their frames following.
        devtools.evaluate(
            "(() => { const fetch = window.fetch; window.placedbGetPlaces = {};"
            " window.fetch = (url, options) => {"
            "   if (!String(url).endsWith('/GetPlace')) return fetch(url, options);"
            "   const id = JSON.parse(options.body).place_id;"
            "   window.placedbGetPlaces[id] = (window.placedbGetPlaces[id] || 0) + 1;"
            "   return new Promise((resolve) => setTimeout(resolve, 1000))"
            "       .then(() => fetch(url, options)); }; })()")
        stored_at = {}  # place id -> when the map first had it as its newest
        shown_at = {}   # place id -> when the live page first showed it (or a newer) as newest
        ingest = subprocess.Popen(
            [placedb.cli, "--address", placedb.address, "ingest", "office", live_frames, "--glob",
             "*.jpg", "--agents", "2", "--rate", "4", "--agent-id", "walker"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        end = None
        while True:
            now = time.monotonic()
            in_map = newest_in_map()
            for place in range(before + 1, in_map + 1):
                stored_at.setdefault(place, now)
            on_page = int(devtools.evaluate(
                "(() => { const card = document.querySelector('#live-places .place-card');"
                " return card ? Number(card.dataset.placeId) : 0; })()"))
            for place in range(before + 1, on_page + 1):
                shown_at.setdefault(place, now)
            if ingest.poll() is not None and end is None:
                end = now
                if ingest.returncode != 0:
                    fail("the live ingest failed: " + ingest.stderr.read())
            if end is not None and on_page >= in_map and in_map > before:
                break
            if end is not None and now - end > 30:
                fail("the live page shows place %d, 30 s after the ingest ended the map's newest "
                     "is %d" % (on_page, in_map))
            time.sleep(0.2)
        if not stored_at:
            fail("the live ingest stored no place")
        delays = sorted(shown_at[p] - stored_at[p] for p in stored_at)
        print("live page: %d places from 2 agents at 4 frames/s; each shown %.1f s (median), "
              "%.1f s (max) after it was stored" % (
                  len(delays), delays[len(delays) // 2], delays[-1]))
        fetched = devtools.evaluate("window.placedbGetPlaces")
        again = {place: n for place, n in fetched.items() if n > 1}
        print("live page: %d GetPlace calls for %d places" % (sum(fetched.values()), len(fetched)))
        if again:
            fail("the live page fetched places again on every refresh: %s" % again)
        if delays[-1] > 5.0:
            fail("the live page showed a place %.1f s after it was stored (deadline 5 s)" %
                 delays[-1])
        if devtools.errors:
            fail("live page error: " + "; ".join(devtools.errors))
    finally:
        shutil.rmtree(live_frames, ignore_errors=True)


def stored_place_query(devtools, map_name, place_id):
    """Queries `map_name` with its stored place `place_id` on the query page; returns how the
    results ended ("yes", "error"), their text and the top match's place id."""
    devtools.evaluate(
        "(() => { const file = document.getElementById('query-file'); file.value = '';"
        " const map = document.getElementById('query-map'); map.value = %s;"
        " document.getElementById('query-place').value = %s;"
        " document.getElementById('query-results').dataset.done = '';"
        " document.getElementById('query-run').click(); })()" % (
            json.dumps(map_name), json.dumps(str(place_id))))
    wait_for("the stored place's query to end", lambda: devtools.evaluate(
        "document.getElementById('query-results').dataset.done !== ''"), timeout=120)
    return devtools.evaluate(
        "(() => { const r = document.getElementById('query-results');"
        " const m = r.querySelector('.match');"
        " return { done: r.dataset.done, text: r.textContent,"
        " top: m ? m.dataset.placeId : null }; })()")


# Frames of the dynamics map: (RTAB-Map frame, UTC hour) with a person box on each, a car on
# every third; taken two days ago.
DYNAMICS_FRAMES = [(frame, (7, 12, 18)[frame % 3]) for frame in range(1, 13)]


def fill_dynamics_map(address, frames_dir, work):
    """Ingests DYNAMICS_FRAMES into map 'traffic' over gRPC with their boxes; returns the stored
    place ids, those with a car, the hours used and their weekday (0 = Monday)."""
    import datetime
    import grpc  # python3-grpcio

    protoc = shutil.which("protoc")
    if not protoc:
        fail("protoc is not installed (protobuf-compiler): the dynamics page's frames are sent "
             "with messages generated from proto/placedb.proto")
    proto_dir = os.path.realpath(os.path.join(os.path.dirname(__file__), "..", "..", "proto"))
    generated = os.path.join(work, "pb")
    os.makedirs(generated)
    subprocess.run([protoc, "-I", proto_dir, "--python_out=" + generated,
                    os.path.join(proto_dir, "placedb.proto")], check=True)
    sys.path.insert(0, generated)
    import placedb_pb2 as pb

    today = datetime.datetime.now(datetime.timezone.utc).replace(hour=0, minute=0, second=0,
                                                                 microsecond=0)
    day = today - datetime.timedelta(days=2)
    frames = []
    for sequence, (frame, hour) in enumerate(DYNAMICS_FRAMES, start=1):
        taken = day + datetime.timedelta(hours=hour, seconds=sequence)
        observation = pb.Observation(agent_id="crossing", sequence=sequence,
                                     timestamp_ns=int(taken.timestamp()) * 1_000_000_000)
        with open(os.path.join(frames_dir, "%d.jpg" % frame), "rb") as image:
            observation.encoded_image.data = image.read()
        observation.boxes.add(class_name="person", confidence=0.9,
                              rect=pb.Rect(x=10, y=40, width=30 + 10 * sequence, height=200))
        if frame % 3 == 0:
            observation.boxes.add(class_name="car", confidence=0.8,
                                  rect=pb.Rect(x=400, y=300, width=200, height=150))
        frames.append(observation)

    def requests():
        yield pb.IngestRequest(header=pb.IngestHeader(map="traffic"))
        for observation in frames:
            yield pb.IngestRequest(observation=observation)

    with grpc.insecure_channel(address) as channel:
        ingest = channel.stream_stream(
            "/placedb.v1.PlaceDb/Ingest", request_serializer=lambda m: m.SerializeToString(),
            response_deserializer=pb.IngestResponse.FromString)
        responses = list(ingest(requests(), timeout=120))
    stored, with_car = [], []
    for response in responses:
        if response.HasField("error"):
            fail("ingesting the dynamics map: " + str(response.error))
        if response.stored:
            stored.append(response.place_id)
            if len(frames[response.index].boxes) > 1:
                with_car.append(response.place_id)
    if len(stored) < len(frames) // 2 or not with_car:
        fail("the dynamics map stored %d of %d frames (%d with a car)" % (
            len(stored), len(frames), len(with_car)))
    return stored, with_car, sorted({hour for _, hour in DYNAMICS_FRAMES}), day.weekday()


# Watches the dynamics page from the moment it is installed: when a first card shows (loading),
# when a first card has its data, when the ranking is shown, GetPlace calls at once.
DYNAMICS_PROBE = """(() => {
  const probe = { firstCardMs: null, firstLoadedMs: null, rankedMs: null, maxInFlight: 0,
                  inFlight: 0 };
  const start = performance.now();
""" + COUNT_GETPLACE_FETCHES + """  const observer = new MutationObserver(() => {
    const now = performance.now() - start;
    if (probe.firstCardMs === null && document.querySelector('#view .dynamics-card')) {
      probe.firstCardMs = now;
    }
    if (probe.firstLoadedMs === null &&
        document.querySelector('#view .dynamics-card[data-state="loaded"]')) {
      probe.firstLoadedMs = now;
    }
    const ranking = document.getElementById('dynamics-ranking');
    if (probe.rankedMs === null && ranking && ranking.dataset.loaded === 'yes') {
      probe.rankedMs = now;
    }
  });
  observer.observe(document.getElementById('view'), { childList: true, subtree: true,
                                                      attributes: true });
  probe.stop = () => { observer.disconnect(); window.fetch = fetch; };
  window.placedbProbe = probe;
})()"""


def check_dynamics_page(devtools, screenshots, stored, with_car, hours, weekday):
    """The dynamics page of map 'traffic': first card within 1 s, the class totals and hours of
    the frames sent, person ranked by default (every place in all its frames), then car: the car
    places first; a ranked place links to its card on the places page."""
    devtools.evaluate(DYNAMICS_PROBE)
    devtools.show("#/dynamics/traffic")
    probe = wait_for("the dynamics page's probe", lambda: devtools.evaluate(
        "window.placedbProbe.firstLoadedMs !== null && window.placedbProbe.rankedMs !== null"
        " ? window.placedbProbe : null"))
    all_drawn = lambda: devtools.evaluate(
        "(() => { const cards = document.querySelectorAll('#dynamics-ranking .ranked-card');"
        " return cards.length > 0 && Array.from(cards).every((c) => c.dataset.state === 'loaded'); })()")
    wait_for("the ranked places' thumbnails", all_drawn)
    devtools.evaluate("window.placedbProbe.stop()")
    print("dynamics page: a first card after %.0f ms, the first with its data after %.0f ms, the "
          "ranking after %.0f ms, %d GetPlace calls at most at once" % (
              probe["firstCardMs"], probe["firstLoadedMs"], probe["rankedMs"],
              probe["maxInFlight"]))
    if probe["firstLoadedMs"] > 1000:
        fail("the dynamics page showed its first card after %.0f ms (deadline 1 s)" %
             probe["firstLoadedMs"])
    if probe["firstCardMs"] > probe["rankedMs"]:
        fail("the dynamics page stayed blank until its ranking was in")
    if probe["maxInFlight"] < 2:
        fail("the dynamics page fetched its places one at a time")

    classes = devtools.evaluate(
        "Array.from(document.querySelectorAll('#dynamics-classes tr.class-row'))"
        ".map((r) => [r.cells[0].textContent, Number(r.cells[1].textContent)])")
    if classes != [["person", len(stored)], ["car", len(with_car)]]:
        fail("the dynamics page's classes are %s, not person in %d frames and car in %d" % (
            classes, len(stored), len(with_car)))
    cells = devtools.evaluate(
        "Array.from(document.querySelectorAll('#dynamics-hours .hour-cell'))"
        ".map((c, i) => [i, Number(c.dataset.observations || 0)]).filter((c) => c[1] > 0)")
    shown_hours = sorted(i % 24 for i, _ in cells)
    if shown_hours != hours or any(i // 24 != weekday for i, _ in cells) or \
            sum(n for _, n in cells) != len(stored):
        fail("the hours chart shows %s, the frames were taken at %s h UTC on weekday %d" % (
            cells, hours, weekday))

    def ranking():
        return devtools.evaluate(
            "Array.from(document.querySelectorAll('#dynamics-ranking .ranked-card')).map((c) =>"
            " [Number(c.dataset.placeId), Number(c.dataset.score),"
            "  c.querySelector('canvas').dataset.thumbnail])")
    ranked = ranking()
    title = devtools.evaluate("document.getElementById('dynamics-ranking-title').textContent")
    if "person" not in title or sorted(p for p, _, _ in ranked) != sorted(stored) or \
            any(score != 1 for _, score, _ in ranked):
        fail("the default ranking (%r) is %s, not every place with person in all its frames" % (
            title, ranked))
    if any(thumbnail != "yes" for _, _, thumbnail in ranked):
        fail("the map keeps thumbnails but ranked places show none: %s" % ranked)
    devtools.screenshot(os.path.join(screenshots, "dynamics.png"))

    # Car from the selector: the car places first (in all their frames), then the others at 0.
    devtools.evaluate(
        "(() => { const s = document.getElementById('dynamics-class');"
        " s.value = Array.from(s.options).find((o) => o.textContent === 'car').value;"
        " document.getElementById('dynamics-ranking').dataset.loaded = '';"
        " s.dispatchEvent(new Event('change')); })()")
    wait_for("the car ranking", lambda: devtools.evaluate(
        "document.getElementById('dynamics-ranking').dataset.loaded === 'yes'"))
    ranked = ranking()
    top = ranked[:len(with_car)]
    if sorted(p for p, _, _ in top) != sorted(with_car) or any(s != 1 for _, s, _ in top) or \
            any(s != 0 for _, s, _ in ranked[len(with_car):]):
        fail("ranking by car shows %s; the car places are %s" % (ranked, with_car))
    if "#/dynamics/traffic/car" not in devtools.evaluate("location.hash"):
        fail("the address does not name the chosen class: " + devtools.evaluate("location.hash"))
    print("dynamics page: classes %s; by car: places %s first of %d" % (
        classes, [p for p, _, _ in top], len(ranked)))

    # A ranked place's link: the places page from that place, its card marked.
    link = devtools.evaluate(
        "document.querySelector('#dynamics-ranking .ranked-card a').getAttribute('href')")
    devtools.show(link)
    chosen = devtools.evaluate(
        "(() => { const c = document.querySelector('#places .place-card.chosen');"
        " return c ? Number(c.dataset.placeId) : null; })()")
    if chosen != top[0][0]:
        fail("the link %s of place %d shows place %s chosen" % (link, top[0][0], chosen))


def console_api(url, method, request):
    call = urllib.request.Request(url + "api/v1/" + method, data=json.dumps(request).encode(),
                                  headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(call, timeout=60) as response:
        return json.loads(response.read())


def main():
    chromium = os.environ.get("PLACEDB_CHROMIUM") or shutil.which("chromium")
    if not chromium:
        if os.environ.get("PLACEDB_SKIP_BROWSER_TEST") == "1":
            print("SKIPPED: chromium is not installed (PLACEDB_SKIP_BROWSER_TEST=1)")
            return SKIP
        fail("chromium is not installed: the console's browser test needs Debian's chromium "
             "(tools/setup.sh --deps installs it; PLACEDB_SKIP_BROWSER_TEST=1 skips locally)")
    try:
        import websocket  # noqa: F401
    except ImportError:
        fail("python3-websocket is not installed (tools/setup.sh --deps installs it)")

    server_binary = env("PLACEDB_SERVER_BINARY")
    cli = env("PLACEDB_CLI_BINARY")
    # Resolved: chromium refuses to read an uploaded file whose path has a ".." part (the
    # default shared directory is <source>/../shared).
    frames_dir = os.path.realpath(os.path.join(env("PLACEDB_SHARED_DIR"), "data", "rtabmap-loop"))
    if not os.path.isfile(os.path.join(frames_dir, "%d.jpg" % FRAMES)):
        fail("RTAB-Map frames missing in " + frames_dir)
    screenshots = env("PLACEDB_CONSOLE_SCREENSHOTS")
    os.makedirs(screenshots, exist_ok=True)

    work = tempfile.mkdtemp(prefix="placedb-console-browser-")
    frames = os.path.join(work, "frames")
    os.makedirs(frames)
    for i in range(1, FRAMES + 1):
        os.symlink(os.path.join(frames_dir, "%d.jpg" % i), os.path.join(frames, "%d.jpg" % i))
    address = "127.0.0.1:%d" % free_port()
    # With the YOLOX-Nano model (tools/install_models.sh), a second map of CamVid street frames
    # with server-side detection shows dynamic-object boxes and dropped keypoints.
    model = os.path.join(os.environ.get("PLACEDB_MODELS_DIR", ""), "yolox_nano.onnx")
    street = os.path.join(env("PLACEDB_SHARED_DIR"), "data", "camvid", "images")
    detector = (["--detector-model", model] if os.path.isfile(model) and os.path.isdir(street)
                else [])
    processes = []
    try:
        server = subprocess.Popen(
            [server_binary, "--listen", address, "--data-dir", os.path.join(work, "data"),
             "--metrics-listen", "off", "--console-listen", "127.0.0.1:0",
             "--vocabulary", "default=" + env("PLACEDB_DEFAULT_VOCABULARY"), "--threads", "2",
             "--log-level", "warn"] + detector,
            stdout=subprocess.DEVNULL, stderr=open(os.path.join(work, "server.log"), "w"))
        processes.append(server)

        def placedb(*args, check=True):
            return subprocess.run([cli, "--address", address] + list(args), check=check,
                                  capture_output=True, text=True)
        placedb.cli = cli
        placedb.address = address

        wait_for("placedb-server to serve",
                 lambda: server.poll() is None and placedb("health", check=False).returncode == 0,
                 timeout=120)
        url = placedb("console").stdout.strip()
        if not re.fullmatch(r"http://127\.0\.0\.1:\d+/", url):
            fail("placedb console printed %r" % url)
        placedb("maps", "create", "office", "--thumbnails", "--verify", "direct")
        placedb("ingest", "office", frames, "--glob", "*.jpg", "--agents", "2",
                "--agent-id", "robot", "--sequence-start", "1", "--camera", OFFICE_CAMERA)
        if detector:
            street_frames = os.path.join(work, "street")
            os.makedirs(street_frames)
            for name in sorted(os.listdir(street))[:12]:
                os.symlink(os.path.join(street, name), os.path.join(street_frames, name))
            placedb("maps", "create", "street", "--thumbnails", "--box-source", "server")
            placedb("ingest", "street", street_frames, "--glob", "*.jpg", "--agent-id", "car-1")
        else:
            print("no detector model in PLACEDB_MODELS_DIR: the street map is left out")
        description = console_api(url, "GetMap", {"name": "office"})
        places = int(description["stats"]["places"])
        if places < FRAMES // 2:
            fail("only %d of %d frames were stored" % (places, FRAMES))
        if not description["config"].get("thumbnails", {}).get("enabled"):
            fail("maps create --thumbnails made a map without thumbnails")

        devtools_port = free_port()
        profile = os.path.join(work, "chromium")
        browser = subprocess.Popen(
            [chromium, "--headless=new", "--no-sandbox", "--disable-gpu",
             "--disable-dev-shm-usage", "--no-first-run", "--disable-extensions",
             "--disable-background-networking", "--disable-sync",
             "--remote-debugging-address=127.0.0.1", "--remote-debugging-port=%d" % devtools_port,
             "--remote-allow-origins=*", "--user-data-dir=" + profile, "about:blank"],
            stdout=subprocess.DEVNULL, stderr=open(os.path.join(work, "chromium.log"), "w"))
        processes.append(browser)

        def page_target():
            try:
                with urllib.request.urlopen("http://127.0.0.1:%d/json/list" % devtools_port,
                                            timeout=5) as response:
                    targets = json.loads(response.read())
            except OSError:
                return None
            pages = [t for t in targets if t.get("type") == "page"]
            return pages[0]["webSocketDebuggerUrl"] if pages else None

        devtools = DevTools(wait_for("chromium's DevTools endpoint", page_target, timeout=60))
        devtools.call("Runtime.enable")
        devtools.call("Page.enable")
        devtools.call("Emulation.setDeviceMetricsOverride", width=1280, height=900,
                      deviceScaleFactor=1, mobile=False)
        devtools.call("Page.navigate", url=url)  # the maps view by default; show() changes the hash
        wait_for("the console to load", lambda: devtools.evaluate(
            "document.getElementById('view') !== null && "
            "document.getElementById('view').dataset.ready === 'yes'"))

        # Maps: the map is listed with its places.
        devtools.show("#/maps")
        row = devtools.evaluate(
            "(() => { const r = document.querySelector('tr.map-row[data-map=\"office\"]');"
            " return r ? Array.from(r.cells).map((c) => c.textContent) : null; })()")
        if not row:
            fail("the maps page does not list 'office'")
        if row[3] != str(places):
            fail("the maps page shows %s places for 'office', the map has %d" % (row[3], places))
        if not row[9].startswith("file "):
            fail("the maps page shows vocabulary %r for 'office', not its file's" % row[9])
        devtools.screenshot(os.path.join(screenshots, "maps.png"))

        # Places: a page of cards, each with its frame drawn (or the placeholder). Every card
        # shows as soon as the listing answers (the first within a second: measured, reported),
        # the frames drawn as their GetPlace calls answer, several at once.
        devtools.evaluate(PLACES_PROBE)
        devtools.show("#/places/office")
        probe = wait_for("the places page's probe", lambda: devtools.evaluate(
            "window.placedbProbe.firstCards !== null && window.placedbProbe.allDrawnMs !== null"
            " ? window.placedbProbe : null"))
        devtools.evaluate("window.placedbProbe.stop()")
        listed = min(24, places)
        print("places page: first %d cards after %.0f ms (%d drawn then), every frame drawn after "
              "%.0f ms, %d GetPlace calls at most at once" % (
                  probe["firstCards"], probe["firstMs"], probe["drawnAtFirst"],
                  probe["allDrawnMs"], probe["maxInFlight"]))
        if probe["firstCards"] != listed:
            fail("the places page showed %d card(s) first, not the listing's %d at once" % (
                probe["firstCards"], listed))
        if probe["maxInFlight"] < 2:
            fail("the places page fetched its places one at a time")
        cards = devtools.evaluate(
            "Array.from(document.querySelectorAll('#places .place-card')).map((c) =>"
            " [c.dataset.placeId, c.querySelector('canvas').dataset.thumbnail])")
        if not cards:
            fail("the places page shows no places")
        if int(cards[0][0]) != places:
            fail("the places page starts at place %s, not the newest (%d)" % (cards[0][0], places))
        if any(thumbnail != "yes" for _, thumbnail in cards):
            fail("the map keeps thumbnails but some places show none: %s" % cards)
        print("places page: %d cards with thumbnails" % len(cards))
        # Filtered by agent: only robot-2's places.
        devtools.evaluate("document.getElementById('filter-agent').value = 'robot-2';"
                          "document.querySelector('#view form.bar button[type=submit]').click()")
        wait_for("robot-2's places", lambda: devtools.evaluate(
            "document.getElementById('places').dataset.loaded === 'yes'"))
        agents = devtools.evaluate(
            "Array.from(document.querySelectorAll('#places .place-card .meta'))"
            ".map((m) => m.textContent)")
        if not agents or any("robot-2" not in text for text in agents):
            fail("filtering by agent robot-2 shows %s" % agents)
        devtools.screenshot(os.path.join(screenshots, "places.png"))
        if detector:
            devtools.show("#/places/street")
            dropped = devtools.evaluate(
                "document.querySelectorAll('#places .place-card canvas[data-thumbnail=\"yes\"]')"
                ".length")
            if not dropped:
                fail("the street map's places show no thumbnails")
            devtools.screenshot(os.path.join(screenshots, "places-street.png"))

        # Query: upload a stored frame with the office's camera; its own place ranks first, and
        # the verified matches show their relative poses (issue 32).
        devtools.show("#/query")
        devtools.evaluate("document.getElementById('query-camera').value = %s"
                          % json.dumps(OFFICE_CAMERA))
        document = devtools.call("DOM.getDocument", depth=-1)
        node = devtools.call("DOM.querySelector", nodeId=document["root"]["nodeId"],
                             selector="#query-file")
        query_path = os.path.join(frames_dir, "%d.jpg" % QUERY_FRAME)
        devtools.call("DOM.setFileInputFiles", files=[query_path], nodeId=node["nodeId"])
        # Done, or an error on the page (an exception, or the message the page shows).
        wait_for("the query's results", lambda: devtools.errors or devtools.evaluate(
            "document.getElementById('query-results').dataset.done === 'yes'"
            " || document.getElementById('status').textContent !== ''"), timeout=120)
        if devtools.errors:
            fail("query page error: " + "; ".join(devtools.errors))
        shown = devtools.evaluate("document.getElementById('status').textContent")
        if shown:
            fail("the query page shows an error: " + shown)
        top = devtools.evaluate(
            "(() => { const m = document.querySelector('#query-results .match');"
            " return m ? m.firstElementChild.textContent : null; })()")
        if not top:
            fail("the query shows no match")
        sequence = re.search(r"#(\d+)$", top.strip())
        if not sequence or int(sequence.group(1)) != QUERY_FRAME:
            fail("top match %r is not frame %d's place" % (top, QUERY_FRAME))
        lines = devtools.evaluate(
            "Number(document.querySelector('#query-results .match canvas').dataset.lines)")
        if "verified" not in top or " not verified" in top or not lines:
            fail("the top match is not drawn verified with its inliers (%s lines): %r" % (lines, top))
        poses = devtools.evaluate(
            "Array.from(document.querySelectorAll('#query-results .match')).map((m) =>"
            " { const p = m.querySelector('.pose');"
            "   return [m.firstElementChild.textContent, p ? p.textContent : null]; })")
        verified = [p for t, p in poses if "verified" in t and " not verified" not in t]
        if not any(p and p.startswith("pose: t (") for p in verified) or \
                any(p is None for p in verified):
            fail("the verified matches do not show their poses: %r" % poses)
        print("query: %d verified matches, poses %r" % (len(verified), verified[:2]))
        print("query: top match %s, %d inlier lines drawn" % (top.strip(), lines))
        devtools.screenshot(os.path.join(screenshots, "query.png"))

        # Query with a stored place (its stored features), on every map: with boxes from the
        # server's detector (box_source server) too, where features carry no pixels to detect on.
        box_sources = {}
        for name in ["office"] + (["street"] if detector else []):
            config = console_api(url, "GetMap", {"name": name})["config"]
            box_sources[name] = config.get("detection", {}).get("box_source")
            newest = int(console_api(url, "GetMap", {"name": name})["stats"]["places"])
            outcome = stored_place_query(devtools, name, newest)
            if outcome["done"] != "yes":
                fail("querying %s's stored place %d (box_source %s) ends %r: %s" % (
                    name, newest, box_sources[name], outcome["done"], outcome["text"]))
            if outcome["top"] != str(newest):
                fail("querying %s's stored place %d: the top match is place %s" % (
                    name, newest, outcome["top"]))
            print("query: %s's stored place %d (box_source %s) matches itself first" % (
                name, newest, box_sources[name]))
        if detector and box_sources.get("street") != "BOX_SOURCE_SERVER":
            fail("the street map's boxes do not come from the server: %r" % box_sources)
        # An error ends "Querying…" with its message (a place that does not exist).
        outcome = stored_place_query(devtools, "office", 999999)
        if outcome["done"] != "error" or "Querying" in outcome["text"] or \
                "NOT_FOUND" not in outcome["text"]:
            fail("a query of a missing place shows %r (done %r), not its error" % (
                outcome["text"], outcome["done"]))
        devtools.errors.clear()
        print("query: a missing place ends with %r" % outcome["text"])

        # Dynamics: a map of frames with person and car boxes.
        placedb("maps", "create", "traffic", "--thumbnails", "--box-source", "agent")
        check_dynamics_page(devtools, screenshots,
                            *fill_dynamics_map(address, frames_dir, work))

        # Live: agents (when the server reports them) and the latest places, refreshed in place.
        devtools.show("#/live")
        latest = devtools.evaluate("document.querySelectorAll('#live-places .place-card').length")
        if not latest:
            fail("the live page shows no places")
        if description.get("agents"):
            rows = devtools.evaluate("document.querySelectorAll('#live-agents tr[data-agent]').length")
            if rows != len(description["agents"]):
                fail("the live page shows %s agents, GetMap reports %d" % (
                    rows, len(description["agents"])))
        first = devtools.evaluate("document.getElementById('live-updated').textContent")
        devtools.evaluate("window.placedbNotReloaded = true")
        wait_for("the live page to refresh", lambda: devtools.evaluate(
            "document.getElementById('live-updated').textContent") != first, timeout=15)
        if not devtools.evaluate("window.placedbNotReloaded === true"):
            fail("the live page reloaded instead of refreshing")
        devtools.screenshot(os.path.join(screenshots, "live.png"))
        follow_live(devtools, url, placedb, frames_dir)
        print("PASS: maps, places, query, dynamics and live pages in chromium; screenshots in " +
              screenshots)
        return 0
    finally:
        for process in reversed(processes):
            process.terminate()
            try:
                process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                process.kill()
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
