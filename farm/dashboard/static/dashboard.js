async function refresh() {
  const live = document.getElementById('live');
  if (!live || live.dataset.live !== '1') return;
  try {
    const q = location.search ? '&' + location.search.slice(1) : '';
    const r = await fetch(location.pathname + '?fragment=1' + q);
    if (r.ok) { live.outerHTML = await r.text(); }
  } finally { setTimeout(refresh, 2500); }
}
setTimeout(refresh, 2500);
async function cancelJob(url) {
  if (!confirm('Cancel this job? Tasks in flight finish; whole shards are committed.')) return;
  const secret = document.querySelector('meta[name=secret]').content;
  const r = await fetch(url, {method: 'POST', headers: {'X-Shaderball-Secret': secret}});
  document.getElementById('cancel-msg').textContent = await r.text();
}
