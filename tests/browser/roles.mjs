// Each role sees only the controls it may use, in Debian's headless
// Chromium: every user logs in, and on each tab every control in the table
// below is shown to exactly the users the table names and hidden (not
// merely disabled) from the others; the platform lists offer only the
// platforms the user may change. The host runs a demo with one set staged
// beside the active one (so the sets table has activate buttons).
// Usage: node roles.mjs URL PASSWORD USER...
// (USER one of: viewer operator control-dev network-dev admin)
import path from 'node:path';
import { check, logIn, openPage, step } from './harness.mjs';

const [url, password, ...users] = process.argv.slice(2);

const everyone = ['viewer', 'operator', 'control-dev', 'network-dev', 'admin'];
const drivers = ['operator', 'admin'];
const developers = ['control-dev', 'network-dev', 'admin'];

// (tab, control, the users who see it). A new role is a new user in these
// lists (and a row of ROLE_MAY in web/app.js).
const CONTROLS = [
  ['live', '#tabs button[data-tab="live"]', everyone],
  ['live', '#tabs button[data-tab="components"]', everyone],
  ['live', '#tabs button[data-tab="sets"]', everyone],
  ['live', '#tabs button[data-tab="drive"]', drivers],
  ['live', '#tabs button[data-tab="recordings"]', developers],
  ['live', '#estop', everyone],
  ['live', '#sim-controls', drivers],
  ['live', '#sim-pause', drivers],
  ['live', '#map', everyone],
  ['components', '#component-upload-section', developers],
  ['components', '#component-upload', developers],
  ['components', '#component-list', everyone],
  ['sets', '#config-upload-section', developers],
  ['sets', '#world-upload-section', ['control-dev', 'admin']],
  ['sets', '#editor-section', developers],
  ['sets', '#rollback', developers],
  ['sets', '#set-list button.activate', developers],
  ['sets', '#replay-section', developers],
  ['sets', '#set-list button.replay', developers],
  ['sets', '#set-list button.show', everyone],
  ['sets', '#graph', everyone],
];

// The platforms each user's lists offer.
const PLATFORMS = {
  'control-dev': ['control'],
  'network-dev': ['network'],
  admin: ['control', 'network'],
};

const { browser, page, artifacts } = await openPage();
let current = page;
try {
  for (const user of users) {
    const context = await browser.newContext({ viewport: { width: 1400, height: 1000 } });
    const tabPage = await context.newPage();
    current = tabPage;
    tabPage.setDefaultTimeout(30000);
    await logIn(tabPage, url, user, password);
    // The sets table is filled once the page has listed the sets.
    await tabPage.waitForSelector('#set-list tbody tr button.show', { state: 'attached' });
    let tab = null;
    for (const [where, selector, who] of CONTROLS) {
      if (where !== tab) {
        await tabPage.click(`#tabs button[data-tab="${where}"]`);
        await tabPage.waitForSelector(`#tab-${where}:not([hidden])`);
        tab = where;
      }
      const nodes = tabPage.locator(selector);
      check((await nodes.count()) > 0, `${user}: no ${selector} in the page`);
      const shown = await nodes.first().isVisible();
      const expected = who.includes(user);
      check(shown === expected, `${user}: ${selector} is ${shown ? 'shown' : 'hidden'}, expected ${expected ? 'shown' : 'hidden'}`);
      if (!expected) {
        // Hidden by the hidden attribute (on it or an ancestor), not disabled.
        const hiddenAttr = await nodes.first().evaluate((n) => !!n.closest('[hidden]'));
        check(hiddenAttr, `${user}: ${selector} is not hidden by the hidden attribute`);
      }
    }
    for (const select of ['#component-platform', '#config-platform', '#editor-platform']) {
      const offered = await tabPage.locator(select).evaluate((s) => [...s.options].filter((o) => !o.hidden && !o.disabled).map((o) => o.textContent));
      const expected = PLATFORMS[user] || [];
      if (expected.length) {
        check(JSON.stringify(offered) === JSON.stringify(expected), `${user}: ${select} offers ${offered}, expected ${expected}`);
        const chosen = await tabPage.locator(select).inputValue();
        check(expected.includes(chosen), `${user}: ${select} has ${chosen} chosen`);
      }
    }
    await tabPage.click('#tabs button[data-tab="live"]');
    await tabPage.screenshot({ path: path.join(artifacts, `role-${user}.png`), fullPage: true });
    step(`${user}: sees only what it may use`);
    await context.close();
  }
  console.log(`ok: ${users.length} roles`);
} catch (err) {
  console.error(String(err));
  await current.screenshot({ path: path.join(artifacts, 'roles-failure.png'), fullPage: true }).catch(() => {});
  await browser.close();
  process.exit(1);
}
await browser.close();
