(function () {
  var data = JSON.parse(document.getElementById('falsify-data').textContent);
  var tip = document.getElementById('tip');
  function place(ev) {
    var pad = 14, x = ev.clientX + pad, y = ev.clientY + pad, r = tip.getBoundingClientRect();
    if (x + r.width > window.innerWidth) x = Math.max(0, ev.clientX - r.width - pad);
    if (y + r.height > window.innerHeight) y = Math.max(0, ev.clientY - r.height - pad);
    tip.style.left = x + 'px'; tip.style.top = y + 'px';
  }
  // A mark's tooltip ships once, as its SVG <title> (read without script too); on first hover
  // it moves into data-tip, so the styled tip shows it and the browser's own does not.
  function tipped(node) {
    for (var el = node; el && el.tagName && el.tagName.toLowerCase() !== 'svg'; el = el.parentNode) {
      if (el.hasAttribute('data-tip')) return el;
      for (var c = el.firstElementChild; c; c = c.nextElementSibling) {
        if (c.tagName.toLowerCase() === 'title') {
          el.setAttribute('data-tip', c.textContent);
          el.removeChild(c);
          return el;
        }
      }
    }
    return null;
  }
  document.addEventListener('mouseover', function (ev) {
    var el = tipped(ev.target);
    if (!el || !el.getAttribute('data-tip')) { tip.style.display = 'none'; return; }
    tip.textContent = el.getAttribute('data-tip');
    tip.style.display = 'block';
    place(ev);
  });
  document.addEventListener('mousemove', function (ev) {
    if (tip.style.display === 'block') place(ev);
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
  }
  var map = document.getElementById('heatmap');
  map.addEventListener('click', function (ev) {
    var cell = ev.target.closest('.cell'); if (cell) showCell(cell);
  });
  map.addEventListener('keydown', function (ev) {
    var cell = ev.target.closest('.cell');
    if (cell && (ev.key === 'Enter' || ev.key === ' ')) { ev.preventDefault(); showCell(cell); }
  });
})();
