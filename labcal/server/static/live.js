// The pages' live parts (no library, no build step).

// Seconds as people read them (the server's `duration` filter, the same words): 45 s, 12 min 05 s, 2 h 05 min.
function duration(s) {
  "use strict";
  if (s === null || s === undefined) { return "—"; }
  s = Math.round(s);
  if (s < 60) { return s + " s"; }
  if (s < 3600) { return Math.floor(s / 60) + " min " + String(s % 60).padStart(2, "0") + " s"; }
  return Math.floor(s / 3600) + " h " + String(Math.floor(s % 3600 / 60)).padStart(2, "0") + " min";
}
//
// The lab's overview: 15 s after the last answer the page is fetched again and its stations and
// runs replace the ones shown, in place: no timed reload (WCAG 2.2.1). A link that had the focus
// gets it back, so a keyboard user keeps their place; one answer at a time, never an older over a newer.
// How long a bench has waited for a person, or been silent, counts on between updates: each such
// duration names its start (data-since, UTC) and is counted again every 5 s on this computer's clock.
(function () {
  "use strict";
  const lab = document.getElementById("lab");
  if (!lab) { return; }
  function ages() {
    for (const shown of lab.querySelectorAll("[data-since]")) {
      const since = Date.parse(shown.dataset.since);
      if (!Number.isNaN(since)) { shown.textContent = duration(Math.max(0, Date.now() - since) / 1000); }
    }
  }
  ages();
  window.setInterval(ages, 5000);
  if (!window.fetch || !window.DOMParser) { return; }
  async function refresh() {
    try {
      const answer = await fetch(window.location.href,
                                 {credentials: "same-origin", signal: AbortSignal.timeout(10000)});
      const fresh = answer.ok && new DOMParser().parseFromString(await answer.text(), "text/html")
        .getElementById("lab");  // none on the sign-in page a lapsed session is sent to
      if (fresh) {
        const focused = lab.contains(document.activeElement) ? document.activeElement.getAttribute("href") : null;
        lab.replaceChildren(...fresh.childNodes);
        ages();
        const again = focused && lab.querySelector('a[href="' + CSS.escape(focused) + '"]');
        if (again) { again.focus(); }
      }
    } catch (e) { /* the server is away for now: the next round asks again */ }
    window.setTimeout(refresh, 15000);
  }
  window.setTimeout(refresh, 15000);
})();

// The run page: the session-authenticated event stream of this run. Every "progress" event carries
// the run's progress; journal events are listed.
(function () {
  "use strict";
  const run = document.getElementById("run");
  if (!run || !window.EventSource) { return; }
  const id = run.dataset.run;
  const $ = (name) => document.getElementById(name);
  const QUIET = new Set(["move", "status", "settle_pool", "segment", "progress", "point", "run"]);

  // A UTC time as the server's pages write it, with this computer's local time beside it where it differs.
  function clock(utc) {
    if (!utc) { return "—"; }
    const when = new Date(utc);
    const local = when.getTimezoneOffset() === 0 ? ""
      : " (" + when.toLocaleTimeString([], {hour: "2-digit", minute: "2-digit", hour12: false}) + " local)";
    return utc.slice(11, 16) + " UTC" + local;
  }

  function show(p) {
    $("done").textContent = p.points_done;
    $("total").textContent = p.points_total === null ? "?" : p.points_total;
    const fill = run.querySelector(".fill");
    if (fill && p.points_total) { fill.style.width = (100 * p.points_done / p.points_total).toFixed(1) + "%"; }
    $("mount").textContent = p.mount ? "y " + p.mount.y_deg + "°, u " + p.mount.u_deg + "°" : "—";
    $("remount").textContent = p.next_remount_in_s !== null ? "in " + duration(p.next_remount_in_s)
      : (p.eta_s !== null ? "none left" : "—");  // no estimate yet: nothing is known
    $("eta").textContent = duration(p.eta_s);
    $("done-at").textContent = clock(p.done_at_utc);
    $("failed").textContent = p.points_failed;
    const waiting = $("waiting");
    waiting.textContent = p.waiting ? p.waiting.text + " since " + p.waiting.utc.slice(11, 19) + " UTC" : "nothing";
    waiting.className = p.waiting ? "alert" : "";
    $("heard").textContent = p.last_heard_utc ? p.last_heard_utc.slice(11, 19) + " UTC" : "—";
    const fault = $("fault");
    fault.textContent = p.last_fault ? p.last_fault.message : "none";
    fault.className = p.last_fault ? "alert" : "";
    // the badge states the run's state as the server derived it (a silent run is "not heard from");
    // a change of status, or a silent run heard again, is shown by deriving it anew
    if (run.dataset.state === "silent" && p.last_heard_utc !== run.dataset.heard) {
      window.location.reload();
      return;
    }
    const status = $("status");
    if (p.status !== run.dataset.status) {
      status.textContent = p.status;
      if (run.dataset.status === "running") { window.setTimeout(() => window.location.reload(), 1000); }
      run.dataset.status = p.status;
    }
  }

  function listed(e) {
    const item = JSON.parse(e.data);
    if (QUIET.has(item.kind) || !item.message) { return; }
    const li = document.createElement("li");
    li.className = item.kind;
    const time = document.createElement("time");
    time.textContent = (item.utc || "").slice(11, 19);
    const kind = document.createElement("b");
    kind.textContent = item.kind;
    li.append(time, " ", kind, " " + (item.text || item.message));
    const list = $("events");
    list.append(li);
    while (list.children.length > 30) { list.removeChild(list.firstChild); }
  }

  const source = new EventSource("/runs/" + id + "/stream?after=" + encodeURIComponent(run.dataset.after));
  source.addEventListener("progress", (e) => show(JSON.parse(e.data)));
  for (const kind of ["prompt", "fault", "answer", "mount", "pause", "resume", "stop", "retry", "link",
                      "discarded", "interrupted"]) {
    source.addEventListener(kind, listed);
  }
})();
