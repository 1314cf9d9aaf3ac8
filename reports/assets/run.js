(function () {
  var data = JSON.parse(document.getElementById('falsify-data').textContent);
  var tip = document.getElementById('tip');
  function place(px, py) {   // beside the point (px, py) of the viewport, kept on screen
    var pad = 14, x = px + pad, y = py + pad, r = tip.getBoundingClientRect();
    if (x + r.width > window.innerWidth) x = Math.max(0, px - r.width - pad);
    if (y + r.height > window.innerHeight) y = Math.max(0, py - r.height - pad);
    tip.style.left = x + 'px'; tip.style.top = y + 'px';
  }
  // A mark's tooltip ships once, as its SVG <title> (read without script too); on first hover
  // it moves into data-tip, so the styled tip shows it and the browser's own does not.
  function tipped(node) {
    for (var el = node; el && el.tagName && el.tagName.toLowerCase() !== 'svg'; el = el.parentNode) {
      if (el.hasAttribute('data-tip')) return el;
      for (var c = el.firstElementChild; c; c = c.nextElementSibling) {
        if (c.tagName.toLowerCase() === 'title') {   // the text stays its accessible name
          el.setAttribute('data-tip', c.textContent);
          el.setAttribute('aria-label', c.textContent);
          el.removeChild(c);
          return el;
        }
      }
    }
    return null;
  }
  function show(el) {
    if (!el || !el.getAttribute('data-tip')) { tip.style.display = 'none'; return false; }
    tip.textContent = el.getAttribute('data-tip');
    tip.style.display = 'block';
    return true;
  }
  document.addEventListener('mouseover', function (ev) {
    if (show(tipped(ev.target))) place(ev.clientX, ev.clientY);
  });
  document.addEventListener('mousemove', function (ev) {
    if (tip.style.display === 'block') place(ev.clientX, ev.clientY);
  });
  // the keyboard's tooltip: on focus, beside the mark; Escape hides it
  document.addEventListener('focusin', function (ev) {
    var el = ev.target.closest && ev.target.closest('svg') ? tipped(ev.target) : null;
    if (show(el)) { var r = el.getBoundingClientRect(); place(r.right, r.top); }
  });
  document.addEventListener('focusout', function () { tip.style.display = 'none'; });
  document.addEventListener('keydown', function (ev) {
    if (ev.key === 'Escape') tip.style.display = 'none';
  });
  var cols = data.samples.columns, rows = data.samples.rows, at = {};
  cols.forEach(function (c, i) { at[c] = i; });
  function fmt(v, c) {
    if (v === null || v === undefined || v === '') return '\u2014';
    if (typeof v === 'number' && (c === 'iou' || c === 'precision' || c === 'recall'))
      return v.toFixed(3);
    return String(v);
  }
  function rowsText(n) { return n + (n === 1 ? ' row' : ' rows'); }   // "1 row", "2 rows"
  function showCell(cell) {
    var key = cell.getAttribute('data-x') + '|' + cell.getAttribute('data-y');
    var sel = document.querySelectorAll('#heatmap .cell.selected');
    for (var s = 0; s < sel.length; s++) sel[s].classList.remove('selected');
    cell.classList.add('selected');
    var box = document.getElementById('selbox');
    ['x', 'y', 'width', 'height'].forEach(function (a) {
      box.setAttribute(a, cell.getAttribute(a));
    });
    box.setAttribute('visibility', 'visible');
    var hits = rows.filter(function (r) { return r[at.cell] === key; });
    hits.sort(function (a, b) {
      var u = a[at.iou], v = b[at.iou];
      if (u === null && v === null) return a[at.eval] - b[at.eval];
      if (u === null) return 1;
      if (v === null) return -1;
      return u - v || a[at.eval] - b[at.eval];
    });
    var table = document.getElementById('cell-table'), body = table.tBodies[0];
    while (body.firstChild) body.removeChild(body.firstChild);
    var show = ['eval', 'x', 'y', 'yaw', 'car_model', 'count', 'background', 'status', 'iou',
                'precision', 'recall', 'reason'];
    if (at.other !== undefined) show.push('other');   // weather, camera, further objects' dims
    hits.forEach(function (r) {
      var tr = document.createElement('tr');
      show.forEach(function (c) {
        var td = document.createElement('td');
        td.textContent = fmt(r[at[c]], c);
        if (typeof r[at[c]] === 'number') td.className = 'num';
        tr.appendChild(td);
      });
      body.appendChild(tr);
    });
    var m = cell.getAttribute('data-miou');
    var total = (data.samples.cells || {})[key] || hits.length;   // rows beyond the cap: CSV
    var count = total > hits.length ? 'the ' + hits.length + ' lowest of ' + rowsText(total)
      : rowsText(hits.length);
    document.getElementById('cell-title').textContent = 'Samples of cell x = ' +
      cell.getAttribute('data-x') + ', y = ' + cell.getAttribute('data-y') + ' (' +
      count + ', mIoU ' + (m ? m : 'none') + ')';
    document.getElementById('cell-hint').hidden = true;
    table.hidden = false;
    table.parentElement.hidden = false;   // its scroll box, a Tab stop once filled
  }
  var map = document.getElementById('heatmap');
  // The map is one Tab stop: the arrow keys move between its cells (row 0, the nearest, is
  // drawn at the bottom), Enter or Space lists a cell's samples. A ring marks the focused cell
  // over its neighbours, in black and white so it shows on every colour.
  // Only cells that hold a sample are drawn (a search leaves most of a fine grid empty), so
  // each knows its column and row (0: the top row drawn) from where it is drawn.
  var cells = map.querySelectorAll('.cell'), ns = map.namespaceURI, byPlace = {};
  var x0 = Infinity, y0 = Infinity, cw = 1, ch = 1;
  for (var k = 0; k < cells.length; k++) {
    cells[k].setAttribute('role', 'button');
    x0 = Math.min(x0, +cells[k].getAttribute('x')); y0 = Math.min(y0, +cells[k].getAttribute('y'));
    cw = +cells[k].getAttribute('width'); ch = +cells[k].getAttribute('height');
  }
  var ncols = 0, nrows = 0;
  function colRow(cell) {
    return [Math.round((+cell.getAttribute('x') - x0) / cw),
            Math.round((+cell.getAttribute('y') - y0) / ch)];
  }
  for (k = 0; k < cells.length; k++) {
    var p = colRow(cells[k]);
    byPlace[p[0] + ',' + p[1]] = cells[k];
    ncols = Math.max(ncols, p[0] + 1); nrows = Math.max(nrows, p[1] + 1);
  }
  function next(c, r, dc, dr) {   // the next drawn cell from (c, r) in a direction, or null
    for (c += dc, r += dr; c >= 0 && r >= 0 && c < ncols && r < nrows; c += dc, r += dr)
      if (byPlace[c + ',' + r]) return byPlace[c + ',' + r];
    return null;
  }
  var ring = document.createElementNS(ns, 'g');
  ring.setAttribute('id', 'focusring');
  ring.setAttribute('visibility', 'hidden');
  ['outer', 'inner'].forEach(function (c) {
    var r = document.createElementNS(ns, 'rect'); r.setAttribute('class', c); ring.appendChild(r);
  });
  map.appendChild(ring);
  function roving(cell) {
    for (var k = 0; k < cells.length; k++) cells[k].setAttribute('tabindex', cells[k] === cell ? '0' : '-1');
  }
  // focus listeners on the figure: on the <svg> itself they would make Chromium focus it
  var fig = map.parentNode;
  fig.addEventListener('focusin', function (ev) {
    var cell = ev.target.closest('.cell'); if (!cell) return;
    roving(cell);
    if (!cell.matches(':focus-visible')) return;   // a click shows its selection box alone
    var x = +cell.getAttribute('x'), y = +cell.getAttribute('y');
    var w = +cell.getAttribute('width'), h = +cell.getAttribute('height');
    for (var r = ring.firstChild; r; r = r.nextSibling) {
      r.setAttribute('x', x - 1); r.setAttribute('y', y - 1);
      r.setAttribute('width', w + 2); r.setAttribute('height', h + 2);
    }
    ring.setAttribute('visibility', 'visible');
  });
  fig.addEventListener('focusout', function () { ring.setAttribute('visibility', 'hidden'); });
  map.addEventListener('click', function (ev) {
    var cell = ev.target.closest('.cell'); if (cell) { roving(cell); showCell(cell); }
  });
  map.addEventListener('keydown', function (ev) {
    var cell = ev.target.closest('.cell'); if (!cell) return;
    if (ev.key === 'Enter' || ev.key === ' ') { ev.preventDefault(); showCell(cell); return; }
    var p = colRow(cell), c = p[0], r = p[1], to;
    if (ev.key === 'ArrowRight') to = next(c, r, 1, 0);
    else if (ev.key === 'ArrowLeft') to = next(c, r, -1, 0);
    else if (ev.key === 'ArrowUp') to = next(c, r, 0, -1);     // farther: the row drawn above
    else if (ev.key === 'ArrowDown') to = next(c, r, 0, 1);
    else if (ev.key === 'Home') to = next(-1, r, 1, 0);
    else if (ev.key === 'End') to = next(ncols, r, -1, 0);
    else return;
    ev.preventDefault();
    if (to) to.focus();
  });
})();
