/**
 * The experiment's wording that a lab is most likely to adapt: consent and instructions.
 */

export const CONSENT_HTML = `
  <div class="text-page consent">
    <h2>Consent</h2>
    <p>In this study you build towers of blocks on the screen. It takes about 30 minutes. You are
    paid for taking part and earn a bonus that depends on how well you do.</p>
    <p>We record your placements, how long you take, and the movements of your mouse over the task.
    The data are stored without your name and used for research only. You may stop at any time by
    closing this window.</p>
    <p>By clicking "I agree" you confirm that you are at least 18 years old, have read this
    information, and agree to take part.</p>
  </div>`;

export function instructionPages(session) {
  const bonus = `${session.currency}${session.bonus_per_unit.toFixed(2)}`;
  return [
    `<div class="text-page">
      <h2>Welcome</h2>
      <p>In this study you stack blocks to build towers that reach out as far as possible to the
      side, like a balcony, without falling down.</p>
      <p>Each tower is built from a sequence of blocks that you see from the start. The first
      block already stands on the ground, in the middle. You place the others one by one, in the
      order given.</p>
    </div>`,
    `<div class="text-page">
      <h2>Reaching out</h2>
      <p>The further your tower reaches to the left or right of the middle, the more you earn:
      ${bonus} per unit of reach, as long as the tower stands.</p>
      <p>But if a block falls, the tower's trial is over and earns nothing. You decide how much
      risk to take.</p>
      <p>A short tutorial follows to show you how it works.</p>
    </div>`,
  ];
}
