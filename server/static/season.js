// The dashboard's season panel: GET /api/stats (sessions, finished calibrations, median time to
// calibrate and slips per day; the data directory against the retention budget), refreshed every
// 30 s. The figures are the service's; the page only lays them out.

import { api } from './common.js';

const $ = (id) => document.getElementById(id);
const DAYS = 7;
const REFRESH_MS = 30000;

function fmtBytes(n) {
  if (n === null || n === undefined) return '–';
  if (n >= 1e9) return `${(n / 1e9).toFixed(2)} GB`;
  if (n >= 1e6) return `${(n / 1e6).toFixed(1)} MB`;
  return `${Math.round(n / 1e3)} kB`;
}
const pct = (x) => (x === null || x === undefined ? '–' : `${Math.round(100 * x)} %`);
const secs = (x) => (x === null || x === undefined ? '–' : `${x.toFixed(1)} s`);

function row(cells, cls) {
  const tr = document.createElement('tr');
  if (cls) tr.className = cls;
  cells.forEach((text, k) => {
    const td = document.createElement('td');
    td.textContent = text;
    if (k > 0) td.className = 'num';
    tr.appendChild(td);
  });
  return tr;
}

export async function loadSeason() {
  const body = $('season-days');
  try {
    const s = await api(`/api/stats?days=${DAYS}`);
    body.replaceChildren(...s.days.map((d) => row([d.day, String(d.sessions), pct(d.finished_share),
      secs(d.median_calibration_s), String(d.slips)])));
    const t = s.total;
    body.appendChild(row([`${DAYS} days`, String(t.sessions), pct(t.finished_share), secs(t.median_calibration_s),
      String(t.slips)], 'total'));
    const disk = s.disk;
    const budget = disk.budget_bytes ? ` of a ${fmtBytes(disk.budget_bytes)} budget` : ' (no --keep-disk budget)';
    $('season-disk').textContent = `data ${fmtBytes(disk.data_dir_bytes)}${budget} · recordings ` +
      `${fmtBytes(disk.recordings_bytes)} · database ${fmtBytes(disk.database_bytes)} · disk free ${fmtBytes(disk.free_bytes)}`;
    $('season-panel').dataset.loaded = String(Date.now());
    $('season-panel').dataset.sessions = String(t.sessions);
  } catch (err) {
    $('season-disk').textContent = `season figures unavailable: ${err.message}`;
  }
}

loadSeason();
setInterval(loadSeason, REFRESH_MS);
