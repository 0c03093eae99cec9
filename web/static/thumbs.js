// Task thumbnails without waiting for them: the Tasks grid and a task page paint at once with placeholders, and each
// image (`img[data-thumb]`) is fetched only once its card comes near the window, at most two at a time and in the
// order they come into view, so a thumbnail the server still has to render (seconds) never holds the page, its
// load event, or the browser's connections that the next click needs. A card that scrolls away before its turn is
// not asked for; leaving the page aborts what is in flight (the server then drops those renders from its queue).
const MAX_IN_FLIGHT = 2;
const queue = [];
const inFlight = new Set();
const controllers = new Set();

function pump() {
  while (inFlight.size < MAX_IN_FLIGHT && queue.length) {
    const img = queue.shift();
    inFlight.add(img);
    load(img).finally(() => { inFlight.delete(img); pump(); });
  }
}

async function load(img) {
  const ctl = new AbortController();
  controllers.add(ctl);
  img.dataset.state = 'loading';
  try {
    const r = await fetch(img.dataset.thumb, { signal: ctl.signal });
    if (!r.ok) throw new Error(`${r.status}`);
    const url = URL.createObjectURL(await r.blob());
    await new Promise((done) => {
      img.onload = done;
      img.onerror = done;
      img.src = url;
    });
    img.classList.remove('thumb-pending');
    img.dataset.state = 'shown';
  } catch (e) {
    if (ctl.signal.aborted) return;
    img.dataset.state = 'failed';
    img.title = `no start view: ${e.message}`;
  } finally {
    controllers.delete(ctl);
  }
}

const seen = new IntersectionObserver((entries) => {
  for (const e of entries) {
    const img = e.target;
    if (img.dataset.state !== 'waiting' && img.dataset.state !== 'queued') continue;
    if (e.isIntersecting && img.dataset.state === 'waiting') {
      img.dataset.state = 'queued';
      queue.push(img);
    } else if (!e.isIntersecting && img.dataset.state === 'queued') {
      const i = queue.indexOf(img);
      if (i >= 0) queue.splice(i, 1);
      img.dataset.state = 'waiting';
    }
  }
  pump();
}, { rootMargin: '200px' });

for (const img of document.querySelectorAll('img[data-thumb]')) {
  img.dataset.state = 'waiting';
  seen.observe(img);
}
window.addEventListener('pagehide', () => { for (const c of controllers) c.abort(); });
